"""Fast paths of PointRing.push (perf) give exactly what the plain numpy expressions give."""
import numpy as np
import pytest

from pointflow.ring import PointRing
from pointflow.ring.ring import MAX_OFFSET

from .helpers import xrange_pts


def _reference_importance(imp):
    imp = np.asarray(imp, dtype=np.float32)
    if not (imp.min() >= 0 and imp.max() < np.inf):
        imp = np.where(np.isfinite(imp) & (imp > 0), imp, 0.0).astype(np.float32)
    return imp


SPECIALS = [0.0, -0.0, 1e-45, 1.0, 3.4e38, np.inf, -np.inf, np.nan, -np.nan, -1.0, -1e-45]


@pytest.mark.parametrize("bad", [None] + SPECIALS)
@pytest.mark.parametrize("dtype", ["float32", "float64", ">f4"])
def test_importance_check_matches_reference(bad, dtype):
    vals = np.array([0.5, 0.25, 2.0, 0.0, 1.0], dtype=np.float64)
    if bad is not None:
        vals[2] = bad
    vals = vals.astype(dtype)
    with PointRing(8, importance_field="importance") as r:
        r.push(xrange_pts(0, 5), importance=vals)
        got = r.snapshot().importance
    ref = _reference_importance(vals)
    assert got.dtype == np.float32
    assert got.tobytes() == ref.tobytes()  # bit for bit (keeps -0.0 where the reference does)


def test_importance_input_not_modified_and_strided():
    imp = np.array([1.0, -1.0, 0.5, np.nan, 2.0, 3.0], np.float32)
    keep = imp.copy()
    with PointRing(8, importance_field="importance") as r:
        r.push(xrange_pts(0, 3), importance=imp[::2])  # strided view
        got = r.snapshot().importance
    assert np.array_equal(imp, keep, equal_nan=True)
    assert got.tolist() == [1.0, 0.5, 2.0]


def test_commit_log_and_dirty_ranges_through_flat_views():
    with PointRing(10) as r:
        r.push(xrange_pts(0, 4), trace_id=(1 << 64) - 1)
        r.push(xrange_pts(4, 6), trace_id=[(1 << 63), 0, 5])
        r.push(xrange_pts(6, 8), trace_id=np.uint64(7))
        ch = r.take_changes()
        assert [t for t, _ in ch.commits] == [(1 << 64) - 1, 1 << 63, 5, 7]
        assert ch.dirty == [(0, 8)]
        r.push(xrange_pts(8, 13))  # wraps: 8..10 and 0..3
        assert r.take_changes().dirty == [(0, 3), (8, 10)]


def _stored_offsets(r, n):
    return np.array(r.arrays["positions"][:n])


@pytest.mark.parametrize("origin", [(0.0, 0.0, 0.0), (6.4e5, 4.9e6, 12.0), (-5e6, 3.0, -16777216.0),
                                    (16777217.0, 1.0, 2.0), (3.0e15, -7.0, 1.0e-3)])
def test_float32_positions_offsets_bit_identical_to_float64_path(origin):
    # float32 input takes a float32 subtraction when the origin is a float32 value; it must store
    # exactly what the float64 subtraction rounded once to float32 stores
    rng = np.random.default_rng(7)
    n = 4000
    o = np.array(origin)
    parts = [
        (o + rng.standard_normal((n, 3)) * 10.0 ** rng.integers(-8, 7, (n, 1))).astype(np.float32),
        rng.integers(0, 2**32, (n, 3), dtype=np.uint64).astype(np.uint32).view(np.float32),  # any bits
        np.array([[np.inf, -np.inf, np.nan], [-0.0, 0.0, 1e-45], [3.4e38, -3.4e38, -1e-45]], np.float32),
    ]
    for p in parts:
        with PointRing(len(p) + 1) as r, np.errstate(all="ignore"):
            r.push(np.asarray(o, np.float64).reshape(1, 3))  # sets the origin to round(origin)
            org = np.array(r.stats().origin)
            res = r.push(p)
            # only points within MAX_OFFSET of the origin on every axis are stored (in order)
            ok = (np.abs(p.astype(np.float64) - org) < MAX_OFFSET).all(axis=1)
            assert res.written == ok.sum() and res.rejected == len(p) - ok.sum()
            got = np.array(r.arrays["positions"][1:1 + res.written])
            ref = (p[ok].astype(np.float64) - org).astype(np.float32)
        assert np.isfinite(got).all()
        same = got.view(np.uint32) == ref.view(np.uint32)
        assert same.all(), (origin, p[ok][~same.all(axis=1)][:3])


def test_float32_and_float64_inputs_store_the_same():
    rng = np.random.default_rng(3)
    p32 = (rng.uniform(-500, 500, (3000, 3)) + [6.4e5, 4.9e6, 30.0]).astype(np.float32)
    with PointRing(5000) as a, PointRing(5000) as b:
        a.push(p32[:1].astype(np.float64))
        b.push(p32[:1].astype(np.float64))
        a.push(p32)
        b.push(p32.astype(np.float64))
        assert np.array_equal(a.arrays["positions"], b.arrays["positions"])
        assert np.array_equal(a.snapshot().positions, b.snapshot().positions)
