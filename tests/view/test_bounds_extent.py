"""The auto camera's clip box (render/process.py CameraController._bounds): the min/max of
every occupied live slot, read in place over the slot ranges, equals the one from the
gathered copy it replaced, for a ring that wraps, a map's live-slot limit and a
non-finite position."""
from __future__ import annotations

import numpy as np
import pytest

from pointflow.render.base import FrameInput
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
    box, clip = CameraController._bounds(f, clip=True)
    pad = 0.1 * (ghi - glo) + 0.5
    assert np.allclose(clip[0], glo - pad + f.origin) and np.allclose(clip[1], ghi + pad + f.origin)


def test_a_non_finite_position_is_left_out():
    rng = np.random.default_rng(4)
    pos = rng.normal(0, 5, (120_000, 3)).astype(np.float32)
    pos[7] = [np.nan, 0.0, 1e9]  # a hidden point (NaN) with a far coordinate: not in the box
    f = _frame(pos, 0, 120_000)
    assert CameraController._extent(f) is None
    _, clip = CameraController._bounds(f, clip=True)
    glo, ghi = _gathered(f)
    assert ghi[2] < 1e8 and np.allclose(clip[1], ghi + 0.1 * (ghi - glo) + 0.5 + f.origin)
