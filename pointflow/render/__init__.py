"""Render tiers (wgpu, gl, cpu) behind one :class:`Renderer` interface, and tier selection.

The tier classes import lazily (``pointflow.render.GlRenderer`` loads moderngl only when
touched), so importing this package never needs a GPU stack.
"""
from __future__ import annotations

from .base import FrameInput, FrameStats, Renderer, RenderError
from .camera import Camera
from .select import crossover_points, fallback_after, select_renderer

_LAZY = {
    "CpuRenderer": "pointflow.render.cpu",
    "GlRenderer": "pointflow.render.gl",
    "WgpuRenderer": "pointflow.render.wgpu_tier",
    "pcg_hash": "pointflow.render.rules",
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'pointflow.render' has no attribute {name!r}")


__all__ = ["Camera", "CpuRenderer", "FrameInput", "FrameStats", "GlRenderer", "RenderError", "Renderer",
           "WgpuRenderer", "crossover_points", "fallback_after", "pcg_hash", "select_renderer"]
