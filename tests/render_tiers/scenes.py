"""Scenes for the tier tests, built directly as FrameInputs (no pipeline, no shared memory).

Every scene returns ``(frame, camera)``; positions are float32 offsets from a float64 origin,
laid out in a ring of ``capacity`` slots starting at ``head`` (so wrap-around is exercised).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from pointflow.config import RenderConfig
from pointflow.render.base import FrameInput
from pointflow.render.camera import Camera


def make_frame(world: np.ndarray, *, origin=(0.0, 0.0, 0.0), capacity: Optional[int] = None, head: int = 0,
               intensity: Optional[np.ndarray] = None, importance: Optional[np.ndarray] = None,
               t_ms: Optional[np.ndarray] = None, rgb: Optional[np.ndarray] = None, now_ms: float = 0.0,
               budget: Optional[int] = None, seed: int = 0, naive_f32: bool = False) -> FrameInput:
    """Place ``world`` (float64 world coordinates) in a ring. ``naive_f32`` stores absolute
    float32 coordinates with origin 0 (what happens without the origin-relative transform)."""
    world = np.asarray(world, np.float64).reshape(-1, 3)
    n = world.shape[0]
    cap = capacity or max(n, 1)
    assert n <= cap
    org = np.zeros(3) if naive_f32 else np.asarray(origin, np.float64)
    slots = (head + np.arange(n)) % cap
    pos = np.zeros((cap, 3), np.float32)
    pos[slots] = (world - org).astype(np.float32)
    imp = np.zeros(cap, np.float32)
    t = np.zeros(cap, np.float64)
    ch = {}
    inten = np.full(cap, np.nan, np.float32)
    inten[slots] = np.linspace(0, 1, n) if intensity is None else intensity
    ch["intensity"] = inten
    if importance is not None:
        imp[slots] = importance
    if t_ms is not None:
        t[slots] = t_ms
    if rgb is not None:
        c = np.zeros((cap, 3), np.uint8)
        c[slots] = rgb
        ch["rgb"] = c
    return FrameInput(positions=pos, importance=imp, t_ingest_ms=t, channels=ch, head=head, size=n,
                      capacity=cap, origin=org, now_ms=now_ms, budget=budget, frame_seed=seed)


def render_cfg(**kw) -> RenderConfig:
    kw.setdefault("size", [160, 120])
    kw.setdefault("color_range", [0.0, 1.0])
    return RenderConfig(**kw)


def terrain(n: int = 20_000, seed: int = 1, extent: float = 50.0) -> np.ndarray:
    """A rolling surface with a few boxes on it (overlaps exercise the depth test)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-extent, extent, (n, 2))
    z = 3 * np.sin(xy[:, 0] / 7) * np.cos(xy[:, 1] / 9)
    box = (np.abs(xy[:, 0] - 10) < 6) & (np.abs(xy[:, 1] + 5) < 6)
    z[box] += 8
    return np.column_stack([xy, z])


def terrain_camera(extent: float = 50.0, aspect: float = 4 / 3) -> Camera:
    return Camera.fit([-extent, -extent, -4], [extent, extent, 12], aspect=aspect)


def sphere_shell(n: int = 10_000, seed: int = 2, r: float = 10.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True) * r * rng.uniform(0.9, 1.0, (n, 1))


def grid_plane(step: float = 0.05, half: float = 2.0, z: float = 0.0) -> np.ndarray:
    """A fine regular grid: float32 rounding at large offsets shows as visible aliasing."""
    g = np.arange(-half, half + step / 2, step)
    x, y = np.meshgrid(g, g)
    return np.column_stack([x.ravel(), y.ravel(), np.full(x.size, z)])
