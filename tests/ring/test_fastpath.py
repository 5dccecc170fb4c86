"""Fast paths of PointRing.push (perf) give exactly what the plain numpy expressions give."""
import numpy as np
import pytest

from pointflow.ring import PointRing

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
