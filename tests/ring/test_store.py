import multiprocessing as mp
import os
import stat
import time

import numpy as np
import pytest

from pointflow.chunk import PointChunk
from pointflow.ring import ChannelSpec, PointRing, RingAttachError, RingConfigError, RingLayout

from .helpers import xrange_pts, xs


def order_x(r):
    return r.snapshot().positions[:, 0].tolist()


@pytest.mark.parametrize("bad", [0, -1, 1.5, "10", None, True])
def test_capacity_must_be_positive_int(bad):
    with pytest.raises(RingConfigError):
        PointRing(bad)


def test_bad_eviction_and_staleness():
    with pytest.raises(RingConfigError):
        PointRing(4, eviction="lru")
    with pytest.raises(RingConfigError):
        PointRing(4, max_staleness_ms=-1)
    with pytest.raises(RingConfigError):
        PointRing(4, channels=["positions"])


def test_fifo_alias():
    with PointRing(4, eviction="fifo") as r:
        assert r.eviction == "drop_oldest"


def test_fifo_order_and_drop_counts():
    with PointRing(5) as r:
        assert r.push(xrange_pts(0, 3)).dropped == 0
        res = r.push(xrange_pts(3, 8))
        assert (res.written, res.dropped) == (5, 3)
        assert order_x(r) == [3, 4, 5, 6, 7]
        s = r.stats()
        assert (s.total_points, s.dropped_points, s.under_pressure, s.head) == (5, 3, True, 3)
        r.push(xs(8))
        assert order_x(r) == [4, 5, 6, 7, 8]
        assert r.stats().dropped_points == 4
        # a chunk larger than the ring keeps its last `capacity` points
        res = r.push(xrange_pts(10, 22))
        assert res.dropped == 5 + 7 and order_x(r) == [17, 18, 19, 20, 21]
        assert r.stats().dropped_points == 16
        for i in range(30, 43):  # single-point pushes around the wrap
            r.push(xs(i))
        assert order_x(r) == [38, 39, 40, 41, 42]


def test_drop_newest_keeps_first_capacity_points():
    with PointRing(6, eviction="drop_newest") as r:
        r.push(xrange_pts(0, 4))
        res = r.push(xrange_pts(4, 10))
        assert (res.written, res.dropped) == (2, 4)
        r.push(xs(99))
        assert order_x(r) == [0, 1, 2, 3, 4, 5]
        assert r.stats().dropped_points == 5


def test_reset_clears_points_and_counters():
    with PointRing(3) as r:
        r.push(xrange_pts(0, 5))
        r.reset()
        s = r.stats()
        assert (s.total_points, s.dropped_points, s.origin) == (0, 0, None)
        assert r.get_point(0) is None
        r.push(xs(7))
        assert order_x(r) == [7]


def test_origin_precision_georeferenced():
    rng = np.random.default_rng(0)
    base = np.array([640_000.123, 4_900_000.456, 5_000_000.789])
    pts = base + rng.uniform(-500, 500, size=(1000, 3))
    with PointRing(2000) as r:
        r.push(pts)
        r.push(pts[::-1].copy())
        origin = np.array(r.stats().origin)
        # the per-axis (lower) median of the first push, rounded
        assert np.array_equal(origin, np.round(np.partition(pts, 499, axis=0)[499]))
        back = r.snapshot().positions
        want = np.concatenate([pts, pts[::-1]])
        off = want - origin
        # exact to the float32 resolution of the offset (half an ulp), not of the absolute value
        tol = np.spacing(np.abs(off).astype(np.float32)).astype(np.float64) / 2
        assert np.all(np.abs(back - want) <= tol + 1e-9)
        assert np.max(np.abs(back - want)) < 1e-4  # float32 of 5e6 would be 0.25 m
        rec = r.get_point(0)
        assert np.allclose(rec.position, pts[0], atol=1e-4, rtol=0)


def test_channels_generation_stamps_and_get_point():
    with PointRing(4, channels=["rgb", "intensity"]) as r:
        r.push(xrange_pts(0, 4), rgb=np.full((4, 3), 200, np.uint8), intensity=np.arange(4.0))
        p = r.get_point(1)
        assert p.channels["intensity"] == 1.0 and p.channels["rgb"].tolist() == [200, 200, 200]
        # new occupants without intensity: the old value must be reported missing, not stale
        r.push(xrange_pts(10, 12), rgb=np.zeros((2, 3), np.uint16))
        p0 = r.get_point(0)
        assert p0.position[0] == 10 and "intensity" not in p0.channels and p0.channels["rgb"].tolist() == [0, 0, 0]
        p2 = r.get_point(2)
        assert p2.channels["intensity"] == 2.0
        snap = r.snapshot()
        assert snap.present["intensity"].tolist() == [True, True, False, False]
        assert np.isnan(snap.channels["intensity"][2:]).all()
        assert p0.generation > p2.generation
        # unknown channels are ignored; missing everything is fine
        r.push(xs(20), bogus=np.ones(1))
        assert r.get_point(2).channels == {}


def test_get_point_empty_slot():
    with PointRing(4) as r:
        assert r.get_point(0) is None
        r.push(xs(1))
        assert r.get_point(1) is None and r.get_point(99) is None
        assert r.get_point(0).position.tolist() == [1, 0, 0]


def test_only_configured_channels_are_allocated():
    with PointRing(1000) as small, PointRing(1000, channels=["intensity"]) as big:
        assert "ch:intensity" not in small.arrays and "ch:intensity" in big.arrays
        assert os.path.getsize("/dev/shm/" + big.name) > os.path.getsize("/dev/shm/" + small.name)


def test_nonfinite_positions_do_not_crash():
    with PointRing(4) as r:
        r.push(np.array([[np.nan, 1, 2], [10.0, 20.0, 30.0]]))
        assert r.stats().origin == (10.0, 20.0, 30.0)


def test_push_chunk_and_commit_log():
    with PointRing(10, channels=["intensity"]) as r:
        c = PointChunk.from_arrays(xrange_pts(0, 3), intensity=np.ones(3, np.float64))
        r.push_chunk(c)
        r.push(xs(5), trace_id=(1 << 63) + 5)
        ch = r.take_changes()
        assert [t for t, _ in ch.commits] == [c.trace_id, (1 << 63) + 5]
        assert ch.dirty == [(0, 4)]
        assert r.take_changes().commits == []


def test_temporal_stats_inclusive_window():
    with PointRing(10) as r:
        r.push(xrange_pts(0, 3))
        time.sleep(0.05)
        r.push(xrange_pts(3, 5))
        t = r.snapshot().t_ingest_ms
        t_old, t_new = float(t[0]), float(t[-1])
        assert t_new > t_old
        # freeze "now" (no dependence on scheduling) so that the window w = now - t_new is
        # exact (Sterbenz: t_new >= now / 2), hence the cutoff now - w is exactly t_new
        now = t_new * 1.5
        w = now - t_new
        r._now_ms = lambda: now
        ts = r.temporal_stats(w)  # cutoff exactly at the newest points: inclusive
        assert ts.count_in_window == 2
        assert ts.newest_age_ms == w
        assert ts.oldest_age_ms == pytest.approx(now - t_old)
        assert r.temporal_stats(w * (1 - 1e-9)).count_in_window == 0  # a hair shorter: excluded
        assert r.temporal_stats(now - t_old + 1e-6).count_in_window == 5
        r.reset()
        assert r.temporal_stats(10).count_in_window == 0


def test_layout_roundtrip_and_pickle():
    import pickle

    lay = RingLayout(10, (ChannelSpec("rgb", "uint8", 3), "intensity"))
    assert RingLayout.from_dict(lay.to_dict()) == lay
    assert pickle.loads(pickle.dumps(lay)) == lay


def test_segment_permissions_and_unguessable_name():
    with PointRing(8) as a, PointRing(8) as b:
        assert a.name != b.name and len(a.name) > 30
        mode = stat.S_IMODE(os.stat("/dev/shm/" + a.name).st_mode)
        assert mode == 0o600


def test_attach_validation(tmp_path):
    with pytest.raises(RingAttachError):
        PointRing.attach("pfring_does_not_exist")
    with pytest.raises(RingAttachError):
        PointRing.attach("../etc/passwd")
    path = "/dev/shm/pfring_testgarbage%d" % os.getpid()
    with open(path, "wb") as f:
        f.write(b"x" * 40000)
    try:
        with pytest.raises(RingAttachError, match="magic"):
            PointRing.attach(os.path.basename(path))
    finally:
        os.unlink(path)
    with PointRing(8, channels=["intensity"]) as r:
        with pytest.raises(RingAttachError, match="layout"):
            PointRing.attach(r.name, layout=RingLayout(8))
        with PointRing.attach(r.name, layout=RingLayout(8, ("intensity",))) as a:
            r.push(xs(1, 2), intensity=np.ones(2))
            assert a.stats().total_points == 2 and not a.owner
        # the attached close did not unlink
        assert os.path.exists("/dev/shm/" + r.name)
    assert not os.path.exists("/dev/shm/" + r.name)


def _child_push(name, start):
    r = PointRing.attach(name)
    for i in range(50):
        r.push(xrange_pts(start + i * 10, start + i * 10 + 10))
    r.close()


def _child_hold_lock_and_die(name):
    r = PointRing.attach(name)
    r.lock().__enter__()
    os._exit(3)  # dies holding the lock


def test_cross_process_push_and_dead_lock_holder():
    ctx = mp.get_context("spawn")
    with PointRing(100_000) as r:
        ps = [ctx.Process(target=_child_push, args=(r.name, k * 10_000)) for k in range(2)]
        for p in ps:
            p.start()
        for p in ps:
            p.join(60)
        assert [p.exitcode for p in ps] == [0, 0]
        s = r.stats()
        assert s.total_points == 1000 and s.write_count == 100
        assert sorted(r.snapshot().positions[:, 0].tolist()) == sorted(
            float(x) for k in range(2) for x in range(k * 10_000, k * 10_000 + 500))
        p = ctx.Process(target=_child_hold_lock_and_die, args=(r.name,))
        p.start()
        p.join(60)
        assert p.exitcode == 3
        r.push(xs(1))  # would hang if the dead holder's lock were not released
        assert r.stats().total_points == 1001


def test_state_survives_writer_restart():
    ctx = mp.get_context("spawn")
    with PointRing(1000) as r:
        p = ctx.Process(target=_child_push, args=(r.name, 0))
        p.start()
        p.join(60)
        # a new "ingest process" continues where the old one stopped
        p = ctx.Process(target=_child_push, args=(r.name, 500))
        p.start()
        p.join(60)
        assert r.stats().total_points == 1000 and r.stats().dropped_points == 0
        assert order_x(r) == list(map(float, range(1000)))


def _owner_child(q, how):
    from pointflow.ring import SlabPair as _SP

    r = PointRing(1000, channels=["intensity"])
    s = _SP.create(r.layout)
    r.push(xrange_pts(0, 10))
    q.put((r.name,) + s.names)
    if how == "raise":
        raise RuntimeError("boom")
    if how == "exit":
        import sys

        sys.exit(2)
    # "leak": return without close(); interpreter exit must still unlink


@pytest.mark.parametrize("how", ["leak", "raise", "exit"])
def test_owner_unlinks_on_every_exit_path(how):
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=_owner_child, args=(q, how))
    p.start()
    names = q.get(timeout=60)
    p.join(60)
    assert p.exitcode is not None
    for n in names:
        assert not os.path.exists("/dev/shm/" + n), (how, n)


def test_attached_close_is_safe_after_owner_close():
    r = PointRing(10)
    a = PointRing.attach(r.name)
    r.close()
    assert a.stats().capacity == 10  # mapping stays valid
    a.close()
    a.close()


def test_pickle_attaches_by_name():
    import pickle

    from pointflow.ring import SlabPair

    with PointRing(10) as r, SlabPair.create(r.layout) as s:
        r.push(xs(1, 2))
        a = pickle.loads(pickle.dumps(r))
        b = pickle.loads(pickle.dumps(s))
        assert not a.owner and a.stats().total_points == 2 and b.names == s.names
        a.close()
        b.close()
