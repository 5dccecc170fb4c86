"""Absurd but finite coordinates cannot poison the ring (issue 14.1): the origin is a median
of the first push's usable points, points too far from it are rejected and counted (never
stored as inf or an overflowed value), and ordinary points beside them arrive exactly."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from pointflow.chunk import PointChunk
from pointflow.ingest.process import Ingestor
from pointflow.ring import PointRing
from pointflow.ring.ring import MAX_OFFSET

BASE = np.array([637_000.0, 849_000.0, 400.0])


def _ordinary(n, seed=0):
    # quarter units: exact in float64 and as float32 offsets of a few hundred units
    rng = np.random.default_rng(seed)
    return BASE + rng.integers(-400, 400, (n, 3)) * 0.25


@pytest.fixture(autouse=True)
def no_numpy_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an overflow warning fails the test
        yield


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_absurd_first_point_neither_becomes_origin_nor_spoils_the_others(dtype):
    good = _ordinary(50)
    if dtype is np.float32:
        good = good.astype(np.float32).astype(np.float64)
    absurd = np.array([[1e30, 2.0, 3.0]]) if dtype is np.float64 else np.array([[3.0e38, -3.0e38, 1.0]])
    pts = np.concatenate([absurd, good]).astype(dtype)
    with PointRing(100) as r:
        res = r.push(pts)
        assert (res.written, res.rejected, res.dropped) == (50, 1, 0)
        st = r.stats()
        assert np.all(np.abs(np.array(st.origin) - BASE) <= 100)  # near the ordinary points, not 1e30
        snap = r.snapshot()
        assert np.isfinite(r.arrays["positions"]).all()
        assert np.array_equal(snap.positions, good)  # bit for bit
        assert st.rejected_points == 1 and st.total_written == 50


def test_a_push_of_only_absurd_points_sets_no_origin():
    with PointRing(100) as r:
        res = r.push(np.array([[1e30, 0.0, 0.0], [np.nan, 1.0, 1.0], [-1e300, 5.0, 5.0]]))
        assert (res.written, res.rejected) == (0, 3) and r.stats().origin is None
        good = _ordinary(10, 1)
        assert r.push(good).written == 10
        assert np.array_equal(r.snapshot().positions, good)


def test_points_past_the_offset_bound_are_rejected_later_too():
    with PointRing(100) as r:
        r.push(_ordinary(10))
        o = np.array(r.stats().origin)
        edge = o + [MAX_OFFSET - 1, 0, 0]  # stored (0.5 unit error bound)
        far = [o + [MAX_OFFSET, 0, 0], o + [0, -MAX_OFFSET * 4, 0], [1e30, 0, 0], o + [0, 0, 1e308]]
        mixed = np.concatenate([_ordinary(5, 2), [edge], far, _ordinary(5, 3)])
        res = r.push(mixed)
        assert (res.written, res.rejected) == (11, 4)
        snap = r.snapshot()
        assert np.isfinite(r.arrays["positions"]).all()
        assert np.array_equal(snap.positions[10:], np.concatenate([_ordinary(5, 2), [edge], _ordinary(5, 3)]))
        assert r.stats().rejected_points == 4


def test_a_few_outliers_do_not_move_the_origin():
    good = _ordinary(9, 4)
    pts = np.concatenate([[[1e15, -1e15, 1e15]], good[:4], [[-1e12, 1e12, 0.0]], good[4:]])
    with PointRing(100) as r:
        res = r.push(pts)
        assert (res.written, res.rejected) == (9, 2)
        assert np.all(np.abs(np.array(r.stats().origin) - BASE) <= 100)


def test_ingest_counts_out_of_range_and_stays_exact():
    with PointRing(1000, channels=["intensity"]) as ring:
        ing = Ingestor(ring, coalesce_points=10_000)
        good = _ordinary(20, 5)
        pos = np.concatenate([[[1e30, 0, 0]], good[:10], [[np.inf, 0, 0]], [[0, -1e25, 0]], good[10:]])
        inten = np.arange(len(pos), dtype=np.float32)
        assert ing.add_chunk(PointChunk(positions=pos, channels={"intensity": inten}))
        ing.flush()
        c = ing.counters
        assert c.drops["out_of_range"] == 2 and c.drops["non_finite"] == 1
        assert c.points_in == c.points_out + sum(c.drops.values()) == 23
        snap = ring.snapshot()
        assert np.array_equal(snap.positions, good)
        assert snap.channels["intensity"].tolist() == [1.0 + i for i in range(10)] + [13.0 + i for i in range(10)]
        assert ring.stats().total_written == c.points_out == 20


def test_pipeline_with_an_absurd_point_counts_it_and_stays_balanced(tmp_path):
    """A real pipeline (file source, ingest, ring, cadence, cpu tier): a scan whose first
    point is at x = 1e30 lands without it; stats say out_of_range 1, accounting balanced."""
    import os

    from pointflow.runtime.pipeline import Pipeline

    good = _ordinary(2000, 6)
    np.save(tmp_path / "scan.npy", np.concatenate([[[1e30, 0.0, 0.0]], good]))
    cfg = {"source": {"transport": "file", "options": {"path": str(tmp_path / "scan.npy"), "realtime": False}},
           "ring": {"max_points": 10_000}, "render": {"backend": "cpu", "size": [64, 48]},
           "supervisor": {"max_restarts": 0}}
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path / "out")) as pipe:
        pipe.wait(60, until=lambda: pipe.stats()["stages"]["ingest"]["points_in"] >= 2001)
        pipe.wait(60, until=lambda: pipe.stats()["ring"]["total_written"] >= 2000)
        stats = pipe.stop()
    ing = stats["stages"]["ingest"]
    assert ing["drops"].get("out_of_range") == 1 and ing["points_out"] == 2000
    assert stats["ring"]["rejected_points"] == 1 and stats["ring"]["total_written"] == 2000
    assert np.all(np.abs(np.array(stats["ring"]["origin"]) - BASE) <= 100)
    acc = stats["accounting"]
    assert acc["ingest_balanced"] and acc["ring_agrees"] and acc["lost_before_ingest"] == 0
    assert not [n for n in stats["shm_segments"] if os.path.exists(os.path.join("/dev/shm", n))]
