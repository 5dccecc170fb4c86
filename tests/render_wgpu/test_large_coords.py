"""Georeferenced coordinates: origin-relative float64 matrices vs a naive float32 model matrix."""
import numpy as np
import pytest

from pointflow.render.camera import Camera

from .helpers import cfg, frame, lit

pytestmark = pytest.mark.gpu

OFFSET = np.array([6.4e5, 4.9e6, 0.0])


def _terrain(n=40_000):
    rng = np.random.default_rng(11)
    xy = rng.uniform(0, 200, size=(n, 2))
    z = 5 * np.sin(xy[:, 0] / 17) * np.cos(xy[:, 1] / 23) + rng.normal(0, 0.2, n)
    return np.column_stack([xy, z])


def _render(make_renderer, world, origin, cam, **kw):
    r = make_renderer(cfg(size=[640, 360], color_by="z", point_size=2.0), len(world), **kw)
    r.render(frame(world - origin, origin=origin), cam)
    return r.read_image()


def test_far_from_origin_renders_like_near_origin(make_renderer):
    world = _terrain()
    cam = Camera.fit(world.min(0), world.max(0))
    home = _render(make_renderer, world, np.zeros(3), cam)
    origin = OFFSET + np.array([12.3, -4.5, 0.7])      # the ring's origin is near, not at, the data
    away = _render(make_renderer, world + OFFSET, origin, cam.translated(OFFSET))
    assert lit(home).mean() > 0.1                       # the scene fills much of the view
    differ = (home != away).any(axis=-1).mean()
    assert differ <= 0.001, f"{differ:.4%} of pixels differ"

    naive = _render(make_renderer, world + OFFSET, origin, cam.translated(OFFSET), naive_float32=True)
    naive_differ = (home != naive).any(axis=-1).mean()
    assert naive_differ > 0.05, f"naive float32 only differs in {naive_differ:.4%} of pixels"
