"""wgpu render tier: compute culling + sampling, indirect draw, picking (see docs/render-wgpu.md)."""
from .device import select_adapter
from .reference import keep_mask, pcg_hash
from .renderer import WgpuRenderer, merge_ranges, resolve_pick

__all__ = ["WgpuRenderer", "select_adapter", "pcg_hash", "keep_mask", "merge_ranges", "resolve_pick"]
