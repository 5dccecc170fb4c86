"""PointRing.push(..., transform=): the points placed as they are written (frames step, one
rigid transform) give what pushing the placed float64 positions gives, to float32 rounding,
through every path of a push (first push choosing the origin, wrap-around, out-of-range
points, drop_newest, importance eviction)."""
import numpy as np
import pytest

from pointflow.frames.kernels import RigidTransform, Scratch
from pointflow.frames.rotation import from_rpy, to_matrix
from pointflow.ring import PointRing
from pointflow.ring.ring import MAX_OFFSET


def _xf(seed=0, far=False):
    rng = np.random.default_rng(seed)
    R = to_matrix(from_rpy(*rng.uniform(-3, 3, 3)))
    t = rng.uniform(-50, 50, 3) + (np.array([4.5e5, 5.1e6, 30.0]) if far else 0.0)  # UTM-like when far
    return RigidTransform(R, t, Scratch())


def _push_both(ring_a, ring_b, src, xf, **ch):
    lo, hi = float(src.min()), float(src.max())
    ra = ring_a.push(src, value_range=xf.bounds(lo, hi), transform=xf, **ch)
    rb = ring_b.push(xf.world(src), **ch)
    assert (ra.written, ra.dropped, ra.rejected) == (rb.written, rb.dropped, rb.rejected)


def _same(ring_a, ring_b):
    a, b = ring_a.snapshot(), ring_b.snapshot()
    assert a.positions.shape == b.positions.shape
    # offsets are float32: R p + (t - o) and (R p + t) - o may round apart by an ulp
    tol = 2.0 * np.spacing(np.abs(b.positions - ring_b.stats().origin).astype(np.float32)).max(initial=0.0)
    assert np.abs(a.positions - b.positions).max(initial=0.0) <= tol + 1e-9
    for k in b.channels:
        assert np.array_equal(a.channels[k], b.channels[k])


@pytest.mark.parametrize("far", [False, True])
@pytest.mark.parametrize("eviction", ["drop_oldest", "drop_newest", "importance"])
def test_transform_push_equals_pushing_placed_points(far, eviction):
    rng = np.random.default_rng(1)
    kw = {"importance_field": "importance"} if eviction == "importance" else {}
    with PointRing(5000, channels=["intensity"], eviction=eviction, **kw) as a, \
            PointRing(5000, channels=["intensity"], eviction=eviction, **kw) as b:
        for i in range(9):  # 9 x 1,700 points: wraps the 5,000-slot ring more than once
            src = rng.uniform(-80, 80, (1700, 3)).astype(np.float32 if i % 2 else np.float64)
            ch = {"intensity": rng.uniform(0, 1, 1700).astype(np.float32)}
            if kw:
                ch["importance"] = rng.uniform(0.1, 1, 1700).astype(np.float32)
            _push_both(a, b, src, _xf(i % 3, far), **ch)
        assert a.stats().origin == b.stats().origin
        _same(a, b)


def test_out_of_range_points_are_refused_as_without_a_transform():
    with PointRing(1000) as a, PointRing(1000) as b:
        xf = _xf(2)
        _push_both(a, b, np.zeros((10, 3), np.float32), xf)  # origin near t
        src = np.zeros((20, 3), np.float32)
        src[::4, 0] = 2 * MAX_OFFSET  # 5 points far beyond the range of float32 offsets
        _push_both(a, b, src, xf)
        assert a.stats().rejected_points == b.stats().rejected_points == 5
        _same(a, b)


def test_bounds_hold_every_placed_coordinate():
    rng = np.random.default_rng(5)
    for i in range(50):
        xf = _xf(i, far=bool(i % 2))
        src = rng.uniform(-rng.uniform(1, 300), rng.uniform(1, 300), (500, 3))
        lo, hi = xf.bounds(float(src.min()), float(src.max()))
        w = xf.world(src)
        assert lo <= w.min() and w.max() <= hi
