"""Issue 31 item 6: every raster method of the wgpu tier, quads included, within 0.1% of the
float64 cpu tier's pixels on an airborne-scan-like scene (georeferenced, colour by z, 2 px
squares, 480x320), with and without eye-dome lighting.

The quads method used to leave the footprint to the rasteriser (snapped corners, top-left
rule) and order points by the hyperbolic float32 depth z/w: 0.08% of pixels off at footprint
edges without EDL and 0.8% with EDL on the autzen scan (EDL spreads every footprint and depth
swap to its neighbours). It now puts the quads' corners on the pixel edges of the footprint's
pixel box, computed as the compute method computes it, and orders by the linear view depth."""
from __future__ import annotations

import dataclasses
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from pointflow.config import EdlConfig, RenderConfig
from pointflow.render.camera import Camera
from pointflow.render.cpu import CpuRenderer

_spec = importlib.util.spec_from_file_location(
    "render_tiers_scenes_quads", Path(__file__).resolve().parents[1] / "render_tiers" / "scenes.py")
S = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(S)  # type: ignore[union-attr]

GEO = np.array([6.37e5, 8.5e5, 130.0])  # a projected-CRS origin (metres), as a LAS file has


def airborne(n: int = 120_000, seed: int = 5) -> np.ndarray:
    """An airborne scan: rolling ground, flat-roofed buildings (walls and roofs), scattered
    tree crowns above the ground (several returns per column, so depth overlaps everywhere)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 300, (n, 2))
    z = 2.0 * np.sin(xy[:, 0] / 23) + 1.5 * np.cos(xy[:, 1] / 17)
    for bx, by, bw, bh, height in ((60, 80, 40, 30, 12), (170, 60, 30, 50, 18), (120, 200, 60, 25, 9)):
        inside = (np.abs(xy[:, 0] - bx) < bw / 2) & (np.abs(xy[:, 1] - by) < bh / 2)
        z[inside] += height
    trees = rng.uniform(0, 300, (60, 2))
    k = n // 5
    pick = rng.integers(0, len(trees), k)
    crown = trees[pick] + rng.normal(0, 3, (k, 2))
    cz = 2.0 * np.sin(crown[:, 0] / 23) + 1.5 * np.cos(crown[:, 1] / 17) + rng.uniform(4, 14, k)
    return np.vstack([np.column_stack([xy, z]), np.column_stack([crown, cz])])


def _scene():
    world = airborne() + GEO
    frame = S.make_frame(world, origin=GEO, capacity=len(world) + 7_000, head=50_000)
    lo, hi = world.min(0), world.max(0)
    cam = Camera.fit(lo, hi, aspect=480 / 320, elevation_deg=45)
    return frame, cam


def _img(r, frame, cam):
    r.render(frame, cam)
    return r.read_image()


@pytest.mark.parametrize("edl", [False, True], ids=["edl-off", "edl-on"])
def test_airborne_scene_within_a_tenth_of_a_percent_of_cpu(make_renderer, raster, edl):
    frame, cam = _scene()
    cfg = RenderConfig(size=[480, 320], point_size=2, color_by="z", color_range="auto",
                       edl=EdlConfig(enabled=edl))
    ref = _img(CpuRenderer(cfg, frame.capacity, list(frame.channels)), frame, cam)
    img = _img(make_renderer(dataclasses.replace(cfg, raster="auto"), frame.capacity, list(frame.channels)),
               frame, cam)
    covered = (ref != ref[0, 0]).any(-1).mean()
    assert covered > 0.15, f"the scene must cover the image ({covered:.1%})"
    d = float((img != ref).any(-1).mean())
    assert d <= 0.001, f"{raster} (edl={edl}) differs from the cpu tier in {d:.3%} of pixels"


@pytest.mark.parametrize("near_first", [True, False])
def test_every_method_orders_by_linear_depth(make_renderer, raster, near_first):
    """Two points 1 cm apart at 500 m (near 0.1, far 10,000): the nearer wins whatever the
    logical order. A z/w depth buffer steps ~6 cm there (the quads method's old depth); the
    quads method now tests ``w * 2^-k``, exact and as fine as the compute keys."""
    cam = Camera(eye=[0.0, 0.0, 0.0], target=[0.0, 1.0, 0.0], near=0.1, far=10_000.0)
    near, far = [0.0, 500.0, 0.0], [0.0, 500.01, 0.0]
    red, blue = [255, 0, 0], [0, 0, 255]
    pts = np.array([near, far] if near_first else [far, near])
    rgb = np.array([red, blue] if near_first else [blue, red], np.uint8)
    f = S.make_frame(pts, rgb=rgb)
    r = make_renderer(RenderConfig(size=[64, 64], color_by="rgb", point_size=3.0), f.capacity, list(f.channels))
    r.render(f, cam)
    assert tuple(int(v) for v in r.read_image()[32, 32, :3]) == tuple(red)
