"""Scene builders for the wgpu tier tests: FrameInputs built directly (no pipeline)."""
from __future__ import annotations

from typing import Optional

import numpy as np

from pointflow.config import RenderConfig
from pointflow.render.base import FrameInput


def cfg(**kw) -> RenderConfig:
    base = dict(size=[320, 240], color_by=None, point_size=2.0, gpu_timestamps=False)
    base.update(kw)
    return RenderConfig(**base)


def frame(world_rel: np.ndarray, *, capacity: Optional[int] = None, head: int = 0, size: Optional[int] = None,
          origin=(0.0, 0.0, 0.0), importance=None, t_ms=None, channels=None, now_ms: float = 0.0,
          ranges=None, dirty=None, budget=None, seed: int = 0) -> FrameInput:
    """Points ``world_rel`` (already origin-relative) in logical order, placed from ``head``."""
    p = np.asarray(world_rel, np.float64).reshape(-1, 3)
    n = p.shape[0]
    cap = capacity or max(n, 1)
    slots = (head + np.arange(n)) % cap
    pos = np.zeros((cap, 3), np.float32)
    pos[slots] = p.astype(np.float32)

    def place(v, dtype, width=None):
        out = np.zeros((cap,) if width is None else (cap, width), dtype)
        if v is not None:
            out[slots] = v
        return out

    chans = {k: place(v, np.uint8 if k == "rgb" else np.float32, 3 if k == "rgb" else None)
             for k, v in (channels or {}).items()}
    return FrameInput(positions=pos, importance=place(importance, np.float32), t_ingest_ms=place(t_ms, np.float64),
                      channels=chans, head=head, size=n if size is None else size, capacity=cap,
                      origin=np.asarray(origin, np.float64), now_ms=now_ms, channel_ranges=dict(ranges or {}),
                      dirty=dirty, budget=budget, frame_seed=seed)


def lit(img: np.ndarray, bg=None) -> np.ndarray:
    """Mask of pixels that differ from the background (top-left pixel unless given)."""
    b = img[0, 0] if bg is None else np.asarray(bg, np.uint8)
    return (img[..., :3] != b[:3]).any(axis=-1)
