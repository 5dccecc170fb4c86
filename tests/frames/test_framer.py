"""The frames step inside the Ingestor on a real shared-memory ring: clouds placed in the
fixed frame, waiting for late transforms, no_transform drops with exact accounting, the
transforms message, deskew per time convention, and frames absent = points as today."""
import logging

import numpy as np
import pytest

from pointflow.chunk import PointChunk
from pointflow.frames import message as tfmsg
from pointflow.frames.config import DeskewConfig, FramesConfig, StaticTransformConfig
from pointflow.frames.message import Transform, Transforms
from pointflow.ingest.process import Ingestor
from pointflow.ring import PointRing

from . import truth as T

EXT = T.extrinsic([0.9, 0.0, 1.7], [0, 2, 0])
EXT_LEFT = T.extrinsic([0.3, 0.8, 1.2], [0, 0, 90])


class Clock:
    def __init__(self):
        self.t = 1_000_000_000

    def __call__(self):
        return self.t


@pytest.fixture
def ring():
    r = PointRing(400_000, channels=["intensity"])
    yield r
    r.close()


def _tf_batch(robot, idx, static=True):
    out = [Transform("odom", "base_link", st, tuple(p), T.matrix_to_quat(R)) for st, R, p in (robot.tf()[i] for i in idx)]
    if static:
        out.append(Transform("base_link", "lidar_top", 0, tuple(EXT[1]), T.matrix_to_quat(EXT[0]), True))
    return Transforms(out, "test")


def _ing(ring, clock=None, **frames):
    cfg = FramesConfig(**{"fixed": "odom", **frames})
    ing = Ingestor(ring, frames=cfg)
    if clock is not None:
        ing.framer.clock = clock
    return ing


def _cloud(n, stamp, frame="lidar_top", seed=0, src="lidar", **ch):
    rng = np.random.default_rng(seed)
    pos = (rng.integers(-40960, 40960, (n, 3)) / 1024.0).astype(np.float32)
    return PointChunk(positions=pos, channels={"intensity": np.arange(n, dtype=np.float32), **ch},
                      source_id=src, stamp_ns=stamp, frame_id=frame, t_recv_ns=0)


def _balanced(ing):
    c = ing.counters
    return c.points_in == c.points_out + sum(c.drops.values()) + ing.queued_points + ing.framer.waiting_points


def test_clouds_between_samples_land_in_the_fixed_frame(ring):
    robot = T.Robot()
    ing = _ing(ring)
    ing.framer.add_transforms(_tf_batch(robot, range(len(robot.stamps))))
    want = []
    for k in range(5):
        stamp = robot.stamps[10 + 7 * k] + 23_000_000  # between two /tf samples
        c = _cloud(1000, stamp, seed=k)
        want.append(T.to_fixed(robot, EXT, c.positions.astype(np.float64), stamp))
        assert ing.add_chunk(c)
    ing.flush()
    got = ring.snapshot().positions
    want = np.concatenate(want)
    assert np.abs(got - want).max() < 2e-5  # float32 offsets from the ring's origin
    st = ing.framer.stats()["sources"]["lidar"]
    assert st["chain"] == "odom <- base_link <- lidar_top" and st["deskew"] == "off" and st["no_transform"] == 0
    assert st["tf_latency_ms"] > 0
    assert _balanced(ing) and ing.counters.points_out == 5000


def test_late_transforms_release_waiting_clouds_in_order_and_stale_ones_drop(ring, caplog):
    robot = T.Robot(n_tf=20)
    clock = Clock()
    ing = _ing(ring, clock, tf_wait_ms=200)
    ing.framer.add_transforms(_tf_batch(robot, range(5)))
    late = _cloud(100, robot.stamps[8] + 10_000_000, seed=1)
    after = _cloud(50, robot.stamps[2] + 10_000_000, seed=2)  # placeable, but behind `late`
    ing.add_chunk(late)
    ing.add_chunk(after)
    ing.flush()
    assert ing.counters.points_out == 0 and ing.framer.waiting_points == 150 and _balanced(ing)
    clock.t += 100_000_000  # within tf_wait_ms the transforms arrive: both go, in order
    assert ing.receive(tfmsg.encode(_tf_batch(robot, range(5, 12), static=False)))
    ing.flush()
    snap = ring.snapshot()
    assert ing.counters.points_out == 150 and snap.channels["intensity"][:100].tolist() == list(range(100))
    want = T.to_fixed(robot, EXT, late.positions.astype(np.float64), late.stamp_ns)
    assert np.abs(snap.positions[:100] - want).max() < 2e-5
    # a stamp after the newest transform: waits, then no_transform
    stale = _cloud(70, robot.stamps[15] + 1, seed=3)
    with caplog.at_level(logging.WARNING):
        ing.add_chunk(stale)
        clock.t += 150_000_000
        ing.flush()
        assert ing.framer.waiting_points == 70
        clock.t += 60_000_000
        ing.flush()
    assert ing.counters.drops == {"no_transform": 70} and ing.framer.waiting_points == 0
    assert ing.framer.stats()["sources"]["lidar"]["no_transform"] == 70 and _balanced(ing)
    msg = [r.getMessage() for r in caplog.records if "no_transform" in r.getMessage()][0]
    assert "'lidar_top'" in msg and f"{stale.stamp_ns / 1e9:.6f}" in msg and "odom -> base_link" in msg


def test_unknown_frame_and_before_history_and_final_drain(ring):
    robot = T.Robot(n_tf=10)
    clock = Clock()
    ing = _ing(ring, clock, tf_wait_ms=50)
    ing.framer.add_transforms(_tf_batch(robot, range(10)))
    ing.add_chunk(_cloud(10, robot.stamps[0] - 1, seed=1))  # before the history: dropped at once
    assert ing.counters.drops == {"no_transform": 10}
    ing.add_chunk(_cloud(20, robot.stamps[3], frame="camera", src="cam"))  # unknown frame: waits
    assert ing.framer.waiting_points == 20
    ing.finish_frames()  # stopping: nothing can place it
    assert ing.counters.drops == {"no_transform": 30} and ing.framer.waiting_points == 0
    st = ing.framer.stats()["sources"]
    assert st["cam"]["no_transform"] == 20 and st["lidar"]["no_transform"] == 10 and _balanced(ing)


def test_wait_buffer_is_bounded(ring):
    robot = T.Robot(n_tf=4)
    ing = _ing(ring, Clock(), max_wait_points=250)
    ing.framer.add_transforms(_tf_batch(robot, range(4)))
    for k in range(4):
        ing.add_chunk(_cloud(100, robot.stamps[-1] + 10 + k, seed=k))
    assert ing.framer.waiting_points == 200
    assert ing.counters.drops == {"tf_wait_overflow": 200} and _balanced(ing)


def test_static_only_chain_from_config_and_loop_or_two_parents_in_messages(ring):
    st = [StaticTransformConfig("base_link", "lidar_top", [0.9, 0, 1.7], rpy_deg=[0, 2, 0]),
          StaticTransformConfig("odom", "base_link", [10, 0, 0], quaternion=[0, 0, 0, 1])]
    ing = _ing(ring, static=st)
    c = _cloud(100, 0)
    ing.add_chunk(c)
    bad = Transforms([Transform("lidar_top", "odom", 5, (0, 0, 0), (0, 0, 0, 1)),          # loop
                      Transform("map", "base_link", 5, (0, 0, 0), (0, 0, 0, 1)),           # second parent
                      Transform("base_link", "lidar_left", 5, (0, 0, 0), (0, 0, 0, 1), True)], "tf")
    ing.framer.add_transforms(bad)
    ing.flush()
    R, t = EXT
    want = c.positions.astype(np.float64) @ R.T + t + [10, 0, 0]
    assert np.abs(ring.snapshot().positions - want).max() < 2e-5
    s = ing.framer.stats()
    assert s["transforms_rejected"] == {"tf_loop": 1, "tf_two_parents": 1} and s["transforms_in"] == 1
    assert ing.receive([b'{"schema": "pointflow.transforms/1", "transforms": [{"parent": "a"}]}']) is False
    assert ing.rejected == {"bad_transform": 1}


def test_frames_absent_points_exactly_as_today(ring):
    other = PointRing(400_000, channels=["intensity"])
    try:
        plain, framed_off = Ingestor(ring), Ingestor(other, frames=FramesConfig())
        assert framed_off.framer is None
        for k in range(3):
            c = _cloud(500, 123 + k, seed=k)
            c.positions = c.positions.astype(np.float64) * 1000.3
            plain.add_chunk(c)
            framed_off.add_chunk(c)
        # a transforms message with frames off is taken and ignored (counted)
        assert framed_off.receive(tfmsg.encode(Transforms([Transform("a", "b", 1, (1, 2, 3), (0, 0, 0, 1))])))
        plain.flush()
        framed_off.flush()
        a, b = ring.snapshot(), other.snapshot()
        assert a.positions.tobytes() == b.positions.tobytes() and tuple(a.origin) == tuple(b.origin)
        assert framed_off.transform_messages == 1 and framed_off.messages_in == 1
    finally:
        other.close()


# ----------------------------------------------------------------------------- deskew
def _sweep(robot, stamp, n=4096, seed=0):
    """One 100 ms sweep: points at 5..60 m, per-point times spread over the sweep."""
    rng = np.random.default_rng(seed)
    az = rng.uniform(0, 2 * np.pi, n)
    r = rng.uniform(5, 60, n)
    pts = np.column_stack([r * np.cos(az), r * np.sin(az), rng.uniform(-2, 2, n)]).astype(np.float32)
    dt = (az / (2 * np.pi) * 100_000_000).astype(np.int64)  # ns after the stamp
    return pts, dt


CONVENTIONS = {
    "t": lambda dt, st: dt.astype(np.uint32),
    "time": lambda dt, st: (dt / 1e9).astype(np.float32),
    "timestamp": lambda dt, st: (st + dt) / 1e9,
    "offset_time": lambda dt, st: dt.astype(np.uint32),
}


@pytest.mark.parametrize("field", list(CONVENTIONS))
def test_deskew_each_convention_within_1mm_and_wrong_without(ring, field):
    robot = T.Robot(speed=10.0, yaw_rate=0.6)
    stamp = robot.stamps[20] + 17_000_000
    pts, dt = _sweep(robot, stamp)
    vals = CONVENTIONS[field](dt, stamp)
    times = stamp + (np.round(vals.astype(np.float64) * 1e9).astype(np.int64) - stamp if field == "timestamp"
                     else (np.round(vals.astype(np.float64) * 1e9).astype(np.int64) if field == "time" else dt))
    truth = T.to_fixed(robot, EXT, pts.astype(np.float64), times)
    out = {}
    for mode in ("auto", "off"):
        r = PointRing(10_000, channels=["intensity"])
        try:
            ing = _ing(r, deskew=mode)
            ing.framer.add_transforms(_tf_batch(robot, range(len(robot.stamps))))
            c = PointChunk(positions=pts, channels={field: vals}, source_id="s", stamp_ns=stamp, frame_id="lidar_top")
            ing.add_chunk(c)
            ing.flush()
            out[mode] = r.snapshot().positions
            assert ing.framer.stats()["sources"]["s"]["deskew"] == ("off" if mode == "off" else
                                                                    next(iter(ing.framer.sources.values())).deskew)
        finally:
            r.close()
    err = np.linalg.norm(out["auto"] - truth, axis=1)
    err_off = np.linalg.norm(out["off"] - truth, axis=1)
    assert err.max() <= 1e-3, err.max()
    assert np.median(err_off) > 0.2  # 10 m/s over a 100 ms sweep: half a metre at the end


def test_deskew_explicit_config_overrides_auto(ring):
    robot = T.Robot()
    stamp = robot.stamps[20]
    pts, dt = _sweep(robot, stamp, n=1000)
    us = (dt // 1000).astype(np.int64)  # a field in µs, name unknown to auto
    ing = _ing(ring, deskew=DeskewConfig(field="when", unit="us", reference="header"))
    ing.framer.add_transforms(_tf_batch(robot, range(len(robot.stamps))))
    ing.add_chunk(PointChunk(positions=pts, channels={"when": us}, source_id="s", stamp_ns=stamp, frame_id="lidar_top"))
    ing.flush()
    truth = T.to_fixed(robot, EXT, pts.astype(np.float64), stamp + us * 1000)
    assert np.linalg.norm(ring.snapshot().positions - truth, axis=1).max() <= 1e-3
    assert "from config" in ing.framer.stats()["sources"]["s"]["deskew"]


def test_a_cloud_that_cannot_be_placed_is_dropped_and_counted_not_raised(ring):
    robot = T.Robot()
    ing = _ing(ring, deskew=DeskewConfig(field="when"))
    ing.framer.add_transforms(_tf_batch(robot, range(len(robot.stamps))))
    bad = _cloud(10, robot.stamps[5], when=np.zeros((10, 3), np.uint32))  # a time field of three per point
    assert ing.add_chunk(bad) and ing.add_chunk(_cloud(20, robot.stamps[5]))
    ing.flush()
    assert ing.counters.drops == {"transform_error": 10} and ing.counters.points_out == 20 and _balanced(ing)


# ----------------------------------------------------------------------------- deskew paths
def _column_sweep(n=20_000, columns=1024, seed=3):
    """Ouster-like: every point carries its column's time (few distinct values, unsorted)."""
    rng = np.random.default_rng(seed)
    az = rng.uniform(0, 2 * np.pi, n)
    r = rng.uniform(5, 80, n)
    pts = np.column_stack([r * np.cos(az), r * np.sin(az), rng.uniform(-2, 8, n)]).astype(np.float32)
    col = np.minimum((az / (2 * np.pi) * columns).astype(np.int64), columns - 1)
    col_t = np.cumsum(rng.integers(97_000, 98_300, columns)) - 97_000  # irregular column stamps
    return pts, col_t[col].astype(np.uint32)


def test_distinct_finds_column_times_without_a_sort_and_refuses_shared_bins():
    from pointflow.frames import deskew as dk
    from pointflow.frames.kernels import Scratch

    s = Scratch()
    _, t = _column_sweep()
    off = t.astype(np.float64)
    values, idx = dk.distinct(off, float(off.min()), float(off.max()), s)
    assert np.array_equal(values, np.unique(off)) and np.array_equal(values[idx], off)
    close = np.array([0.0, 1e8, 1234567.0, 1234568.0])  # two values 1 ns apart share a bin
    assert dk.distinct(close, 0.0, 1e8, s) is None
    many = np.arange(dk.MAX_DISTINCT + 1, dtype=np.float64) * 1000.0  # one per bin, too many
    assert dk.distinct(many, 0.0, float(many[-1]), s) is None
    one = np.full(5, 7.0)
    values, idx = dk.distinct(one, 7.0, 7.0, s)
    assert values.tolist() == [7.0] and idx.tolist() == [0] * 5


@pytest.mark.parametrize("kind", ["columns", "continuous"])
def test_deskew_equals_tf2_per_point_on_both_paths(ring, kind):
    """Column times take the exact-pose-per-time path, continuous times the node path; both
    against tf2's own lookup at every point's time (buffer.lookup_many, per point)."""
    robot = T.Robot(speed=10.0, yaw_rate=0.6)
    stamp = robot.stamps[20] + 17_000_000
    if kind == "columns":
        pts, t = _column_sweep()
    else:
        pts, dt = _sweep(robot, stamp, n=20_000)
        t = dt.astype(np.uint32)
    ing = _ing(ring)
    ing.framer.add_transforms(_tf_batch(robot, range(len(robot.stamps))))
    placed = ing.framer.submit(PointChunk(positions=pts, channels={"t": t}, source_id="s", stamp_ns=stamp,
                                          frame_id="lidar_top"), pts, {})
    out = placed[0][1]
    Rp, tp = ing.framer.buffer.lookup_many("odom", "lidar_top", stamp + t.astype(np.int64))
    exact = np.einsum("nij,nj->ni", Rp, pts.astype(np.float64)) + tp
    err = np.linalg.norm(out - exact, axis=1)
    truth = T.to_fixed(robot, EXT, pts.astype(np.float64), stamp + t.astype(np.int64))
    assert np.linalg.norm(out - truth, axis=1).max() <= 1e-3
    # exact per distinct time; node interpolation: chord of <= 1 mrad turns, < 20 um at 80 m
    assert err.max() <= (1e-9 if kind == "columns" else 2e-5), err.max()


def test_rigid_transforms_left_to_the_ring_place_points_as_before(ring):
    """Ingest hands one rigid transform per cloud to the ring (applied as it writes): small
    clouds of a static chain still go in one push, big clouds of a dynamic chain too; small
    clouds of a dynamic chain are placed first. Points and counts as if placed in the frames
    step; non-finite points dropped and counted."""
    st = [StaticTransformConfig("odom", "cam", [3.0, -2.0, 1.7], rpy_deg=[1.0, 2.0, 30.0])]
    robot = T.Robot()
    ing = _ing(ring, static=st)
    assert ing.framer.lazy
    ing.framer.add_transforms(_tf_batch(robot, range(len(robot.stamps))))
    Rs = T.extrinsic([3.0, -2.0, 1.7], [1.0, 2.0, 30.0])
    want = []
    for k in range(6):  # small clouds, static chain: coalesced into one push
        c = _cloud(500, 0, frame="cam", seed=k, src="cam")
        if k == 2:
            c.positions[7] = np.nan
        assert ing.add_chunk(c)
        p = c.positions.astype(np.float64)
        want.append(np.delete(p, 7, axis=0) @ Rs[0].T + Rs[1] if k == 2 else p @ Rs[0].T + Rs[1])
    pushes = ing.pushes
    ing.flush()
    assert ing.pushes == pushes + 1
    for k, n in enumerate((600, 15_000)):  # dynamic chain: a small cloud, a big one
        stamp = robot.stamps[12 + 5 * k] + 31_000_000
        c = _cloud(n, stamp, seed=10 + k)
        assert ing.add_chunk(c)
        want.append(T.to_fixed(robot, EXT, c.positions.astype(np.float64), stamp))
    ing.flush()
    got = ring.snapshot().positions
    assert np.abs(got - np.concatenate(want)).max() < 2e-5
    assert ing.counters.drops == {"non_finite": 1} and _balanced(ing) and ing.counters.points_out == 3000 - 1 + 15_600


def test_static_chain_fast_path_follows_changes_of_the_tree(ring):
    """The second cloud of a static chain skips the lookup (same transform object); a new
    static transform on that chain, or a dynamic edge put in it, is used from the next cloud."""
    ing = _ing(ring, static=[StaticTransformConfig("odom", "cam", [3.0, 0.0, 0.0], rpy_deg=[0, 0, 0])])
    fr = ing.framer
    got = [fr.submit(_cloud(50, 0, frame="cam", seed=k, src="cam"), _cloud(50, 0, seed=k).positions, {})[0][1]
           for k in range(2)]
    assert got[0].xf is got[1].xf and fr.sources["cam"].fast is not None
    fr.add_transforms(Transforms([Transform("odom", "cam", 0, (0.0, 5.0, 0.0), (0, 0, 0, 1), True)], "tf"))
    c = _cloud(50, 0, frame="cam", seed=3, src="cam")
    p = fr.submit(c, c.positions, {})[0][1]
    assert p.xf is not got[0].xf and np.allclose(p.xf.world(c.positions), c.positions.astype(np.float64) + [0, 5, 0])
    # other edges change (the buffer's version moves): looked up again, the same placement
    robot = T.Robot()
    fr.add_transforms(_tf_batch(robot, range(len(robot.stamps))))
    c = _cloud(50, 0, frame="cam", seed=4, src="cam")
    q = fr.submit(c, c.positions, {})[0][1]
    assert np.array_equal(q.xf.world(c.positions), p.xf.world(c.positions))
    assert fr.stats()["sources"]["cam"]["clouds"] == 4 and fr.stats()["sources"]["cam"]["chain"] == "odom <- cam"


def test_scratch_keeps_small_buffers_and_drops_huge_ones():
    from pointflow.frames.kernels import KEEP_MAX, Scratch

    s = Scratch()
    a = s.get("x", (1000, 3))
    assert np.shares_memory(a, s.get("x", (500, 3)))  # kept and reused
    big = s.get("y", (KEEP_MAX + 1,))
    assert big.shape == (KEEP_MAX + 1,) and not np.shares_memory(big, s.get("y", (KEEP_MAX + 1,)))
