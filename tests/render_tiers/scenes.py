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


# --------------------------------------------------------------------------- agreement scenes
#: The tier-agreement scenes (test_agreement.py, test_edl.py): name -> () -> (frame, camera,
#: render config overrides). Together they cover every colour mode and a georeferenced origin.
GEO = np.array([6.4e5, 4.9e6, 120.0])


def _terrain():
    w = terrain(20_000)
    f = make_frame(w, capacity=24_000, head=20_000, intensity=((w[:, 2] + 3) / 14).astype(np.float32))
    return f, terrain_camera(), dict(point_size=2)


def _sphere():
    w = sphere_shell(15_000)
    f = make_frame(w, intensity=np.linspace(0, 1, len(w), dtype=np.float32))
    cam = Camera(eye=[30, -25, 12], target=[0, 0, 0], near=5, far=80)
    return f, cam, dict(point_size=5, point_shape="round", colormap="viridis")


def _geo_height():
    w = terrain(15_000) + GEO
    f = make_frame(w, origin=GEO)
    cam = terrain_camera().translated(GEO)
    return f, cam, dict(point_size=3, color_by="z", color_range="auto", colormap="grayscale")


def _world_rgb_filters():
    w = terrain(20_000, seed=7)
    rgb = (np.abs(w) * 9 % 255).astype(np.uint8)
    t = np.linspace(0, 1000, len(w))
    imp = np.abs(np.sin(w[:, 0])).astype(np.float32)
    f = make_frame(w, capacity=22_000, head=15_000, rgb=rgb, t_ms=t, importance=imp, now_ms=1000.0, seed=11)
    return f, terrain_camera(), dict(point_size=0.4, point_size_space="world", color_by="rgb",
                                     time_window_ms=700.0, importance_sampling=True)


SCENES = {"terrain": _terrain, "sphere": _sphere, "georeferenced": _geo_height, "world_rgb_filters": _world_rgb_filters}


# --------------------------------------------------------------------------- eye-dome lighting
WALL_FRONT_RGB = (200, 60, 60)
WALL_BACK_RGB = (60, 200, 60)


def walls(step: float = 0.1):
    """A wall in front of a wall, both facing the camera (constant depth each, so EDL
    darkens only where the near wall's outline meets the far one): back wall at y = 20,
    front wall at y = 10 over the left-centre. Returns (frame, camera, config overrides)."""
    def plane(x0, x1, z0, z1, y):
        x, z = np.meshgrid(np.arange(x0, x1, step), np.arange(z0, z1, step))
        return np.column_stack([x.ravel(), np.full(x.size, y), z.ravel()])
    back, front = plane(-16, 16, -12, 12, 20.0), plane(-8, 0, -3, 3, 10.0)
    rgb = np.vstack([np.tile(WALL_BACK_RGB, (len(back), 1)), np.tile(WALL_FRONT_RGB, (len(front), 1))])
    f = make_frame(np.vstack([back, front]), rgb=rgb.astype(np.uint8))
    cam = Camera(eye=[0, 0, 0], target=[0, 1, 0], near=1, far=100)
    return f, cam, dict(point_size=2, color_by="rgb", background=[0.0, 0.0, 0.0])
