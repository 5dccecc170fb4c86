"""Renderers by tier name and image error against a reference, for the drivers that compare
tiers or render settings (bench_tiers.py, bench_lod_fill.py)."""
from __future__ import annotations

import sys
from typing import Optional

import numpy as np

from pointflow.config import RenderConfig
from pointflow.render.base import Renderer
from pointflow.render.cpu import CpuRenderer

__all__ = ["make_tier", "errors"]


def make_tier(tier: str, cfg: RenderConfig, capacity: int) -> Optional[Renderer]:
    """A renderer of ``tier`` (cpu, cpu-compute, gl, wgpu-quads, wgpu-compute), or None with a
    line on stderr where this machine cannot make it (the driver goes on with the others)."""
    try:
        if tier == "cpu":  # the float64 reference (render.raster: reference)
            return CpuRenderer(cfg, capacity, ["intensity"])
        if tier == "cpu-compute":  # the cpu tier's compiled raster (render.raster: compute)
            from pointflow.render.cpu_compute import CpuComputeRenderer
            return CpuComputeRenderer(cfg, capacity, ["intensity"])
        if tier == "gl":
            from pointflow.render.gl import GlRenderer
            return GlRenderer(cfg, capacity, ["intensity"])
        from dataclasses import replace

        from pointflow.render.wgpu_tier import WgpuRenderer
        if tier.startswith("wgpu-"):  # wgpu-quads / wgpu-compute: one raster method
            cfg = replace(cfg, raster=tier[5:])
        return WgpuRenderer(cfg, capacity, ["intensity"])
    except Exception as exc:  # noqa: BLE001 - report and go on with the other tiers
        print(f"  [{tier}] unavailable: {type(exc).__name__}: {exc}", file=sys.stderr)
        return None


def errors(img: np.ndarray, ref: np.ndarray, bg: np.ndarray) -> dict[str, float]:
    """PSNR (RGB), the share of pixels that differ, and the IoU of lit (non-``bg``) pixels."""
    d = img[..., :3].astype(np.float64) - ref[..., :3]
    mse = float((d * d).mean())
    psnr = float("inf") if mse == 0 else 10 * np.log10(255.0 ** 2 / mse)
    a, b = (img != bg).any(axis=-1), (ref != bg).any(axis=-1)
    union = int((a | b).sum())
    return {"psnr_db": psnr, "diff_fraction": float((img != ref).any(axis=-1).mean()),
            "coverage_iou": float((a & b).sum() / union) if union else 1.0}
