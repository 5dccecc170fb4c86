"""The auto camera's clip box (render/view/controller.py CameraController._clip_box): the
min/max of every occupied live slot, read in place over the slot ranges, equals the one from
the gathered copy it replaced, for a ring that wraps, a map's live-slot limit and a
non-finite position; and it follows the ring at once, not a second later."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pointflow.render.base import FrameInput
from pointflow.config import load_config
from pointflow.render.view import controller
from pointflow.render.view.controller import CameraController


def _frame(pos, head, size, live=None) -> FrameInput:
    return FrameInput(positions=pos, importance=None, t_ingest_ms=None, channels={}, head=head, size=size,
                      capacity=len(pos), origin=np.array([100.0, -5.0, 2.0]), now_ms=0.0, live_slots=live)


def _gathered(f: FrameInput):
    slots = f.occupied_slots()
    if f.live_slots is not None:
        slots = slots[slots < f.live_slots]
    q = f.positions[slots]
    q = q[np.isfinite(q).all(axis=1)]
    return q.min(axis=0).astype(np.float64), q.max(axis=0).astype(np.float64)


@pytest.mark.parametrize("head,size,live", [(0, 200_000, None), (150_000, 200_000, None), (150_000, 200_000, 190_000),
                                            (10, 5, None)])
def test_extent_equals_the_gathered_min_max(head, size, live):
    rng = np.random.default_rng(3)
    pos = rng.normal(0, 50, (250_000, 3)).astype(np.float32)
    pos[(head + size) % len(pos)] = 1e6  # an unoccupied slot: never in the box
    f = _frame(pos, head, size, live)
    lo, hi = CameraController._extent(f)
    glo, ghi = _gathered(f)
    assert np.array_equal(lo, glo) and np.array_equal(hi, ghi)
    clip = CameraController._clip_box(f)
    pad = 0.1 * (ghi - glo) + 0.5
    assert np.allclose(clip[0], glo - pad + f.origin) and np.allclose(clip[1], ghi + pad + f.origin)


def test_a_non_finite_position_is_left_out():
    rng = np.random.default_rng(4)
    pos = rng.normal(0, 5, (120_000, 3)).astype(np.float32)
    pos[7] = [np.nan, 0.0, 1e9]  # a hidden point (NaN) with a far coordinate: not in the box
    f = _frame(pos, 0, 120_000)
    assert CameraController._extent(f) is None
    clip = CameraController._clip_box(f)
    glo, ghi = _gathered(f)
    assert ghi[2] < 1e8 and np.allclose(clip[1], ghi + 0.1 * (ghi - glo) + 0.5 + f.origin)


def test_the_planes_hold_points_that_came_a_moment_later(monkeypatch):
    """Half a scene, then the other half 30 ms later (two sources): the planes of the next
    camera hold both halves. Taken once a second, the later half (farther from a camera above)
    fell behind the far plane and a still scene stayed half drawn."""
    g = np.stack(np.meshgrid(np.arange(0, 20, 0.25), np.arange(0, 20, 0.25)), -1).reshape(-1, 2)
    near_half = np.c_[g, np.full(len(g), 3.0)].astype(np.float32)
    far_half = np.c_[g, np.zeros(len(g))].astype(np.float32)
    pos = np.zeros((20_000, 3), np.float32)
    pos[:len(g)] = near_half
    ctl = CameraController(load_config({"source": {"transport": "synthetic"}}), 160, 120)
    eye, target, up = np.array([10.0, 10.0, 40.0]), np.array([10.0, 10.0, 0.0]), np.array([0.0, 1.0, 0.0])
    f = FrameInput(positions=pos, importance=None, t_ingest_ms=None, channels={}, head=0, size=len(g),
                   capacity=len(pos), origin=np.zeros(3), now_ms=0.0)
    ctl.refresh(f)
    near, far = ctl.planes(eye, target, up, 60.0)
    assert far < 40.0, "the first half alone: the plane z = 0 lies beyond the far plane"
    pos[len(g):2 * len(g)] = far_half
    f2 = FrameInput(positions=pos, importance=None, t_ingest_ms=None, channels={}, head=0, size=2 * len(g),
                    capacity=len(pos), origin=np.zeros(3), now_ms=30.0)
    monkeypatch.setattr(controller, "CLIP_SHARE", 1e12)  # a box that costs nothing (a small ring, idle)
    ctl.refresh(f2)  # a handoff while the ring moves: the box is taken again
    assert ctl.planes(eye, target, up, 60.0)[1] > 40.0
    # a ring whose box costs much (as if huge, or a busy machine) waits while it moves ...
    monkeypatch.setattr(controller, "CLIP_SHARE", 1e-12)
    pos[2 * len(g):3 * len(g)] = far_half - [0.0, 0.0, 5.0]
    f3 = dataclasses.replace(f2, size=3 * len(g), now_ms=60.0)
    ctl.refresh(f3)
    assert ctl.planes(eye, target, up, 60.0)[1] < 45.0, "the box was taken at once: the test shows nothing"
    ctl.refresh(f3)  # ... and is taken at the next look at a ring that stopped (a handoff, the save's draw)
    near, far = ctl.planes(eye, target, up, 60.0)
    assert near < 37.0 and far > 45.0, (near, far)
