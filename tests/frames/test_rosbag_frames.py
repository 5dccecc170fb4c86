"""Frames end to end on bags written by the test: a robot driving an arc with two lidars
(one rotated), /tf at 20 Hz and /tf_static, clouds stamped between transform samples;
through the real source and ingest processes into the ring, ROS 1 and ROS 2."""
import numpy as np
import pytest

from pointflow.frames.buffer import TransformBuffer  # noqa: F401 - (imports must work in the test env)

from ingest import ros_util as ru
from ingest.stage_util import base_config
from . import truth as T
from .bags import BagWriter

SEC = T.SEC
EXTS = {"lidar_top": T.extrinsic([0.9, 0.0, 1.7], [0, 2, 0]),
        "lidar_left": T.extrinsic([0.3, 0.8, 1.2], [5, -10, 90])}


def _bag(tmp_path, kind, static_in_bag=True, deskew_field=None, n=400):
    robot = T.Robot(n_tf=81)  # 4 s of /tf at 20 Hz
    path = tmp_path / ("rec.bag" if kind == "ros1" else f"rec_{kind}")
    w = BagWriter(path, kind)
    t0 = robot.t0
    if static_in_bag:
        w.tf("/tf_static", t0, [("base_link", ch, t0, t, T.matrix_to_quat(R)) for ch, (R, t) in EXTS.items()])
    for st, R, p in robot.tf():
        w.tf("/tf", st + 2_000_000, [("odom", "base_link", st, p, T.matrix_to_quat(R))])  # ROS 1 style leading /
    rng = np.random.default_rng(7)
    expected, clouds = [], []
    for k in range(30):
        topic, frame = ("/top/points", "lidar_top") if k % 2 == 0 else ("/left/points", "lidar_left")
        stamp = t0 + SEC // 10 + k * (SEC // 10) + 23_000_000  # between /tf samples
        pos = (rng.integers(-30720, 30720, (n, 3)) / 1024.0).astype(np.float32)
        fields = {"intensity": np.full(n, k, np.float32)}
        times = stamp
        if deskew_field:
            dt = np.sort(rng.integers(0, 100_000_000, n))
            fields[deskew_field] = dt.astype(np.uint32)
            times = stamp + dt
        # recorded 5 ms after the stamp: before the /tf sample that brackets it (the cloud must wait)
        w.cloud(topic, stamp + 5_000_000, stamp, ("/" if kind == "ros1" else "") + frame, pos, fields)
        expected.append(T.to_fixed(robot, EXTS[frame], pos.astype(np.float64), times))
        clouds.append(n)
    # unknown frame, and a stamp after the newest /tf: both no_transform
    w.cloud("/cam/points", t0 + 2 * SEC, t0 + 2 * SEC, "camera", np.zeros((11, 3), np.float32))
    w.cloud("/top/points", robot.stamps[-1] + SEC // 10, robot.stamps[-1] + SEC // 100, "lidar_top",
            np.zeros((13, 3), np.float32), {"intensity": np.zeros(13, np.float32)})
    w.write()
    return path, expected, robot


def _run(path, frames, expected, extra_good=0):
    cfg = base_config()
    cfg["ring"]["extra_channels"] = ["intensity"]
    cfg["source"] = {"transport": "rosbag", "name": "bag", "options": {"path": str(path), "rate": 0}}
    cfg["frames"] = frames
    total = sum(e.shape[0] for e in expected) + 11 + 13
    st = ru.SourceIngest(cfg)
    try:
        stats = st.wait_ingest(lambda s: s["points_in"] == total and s["points_out"] + sum(s["drops"].values()) == total,
                               timeout=120)
        snap = st.ring.snapshot()
        return stats, snap, st.stage_stats.get("source", {})
    finally:
        st.close()


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
def test_two_lidars_on_a_moving_robot_land_where_the_matrix_model_says(tmp_path, kind):
    path, expected, _ = _bag(tmp_path, kind)
    stats, snap, src = _run(path, {"fixed": "odom", "tf_wait_ms": 2000}, expected)
    assert stats["drops"] == {"no_transform": 24} and stats["points_out"] == 30 * 400
    order = np.argsort(snap.channels["intensity"], kind="stable")  # cloud k has intensity k
    got = snap.positions[order]
    want = np.concatenate(expected)
    assert np.abs(got - want).max() < 5e-5  # float32 offsets from the ring origin (~100 m away)
    fr = stats["frames"]["sources"]
    assert fr["bag:/top/points"]["chain"] == "odom <- base_link <- lidar_top"
    assert fr["bag:/left/points"]["chain"] == "odom <- base_link <- lidar_left"
    assert fr["bag:/cam/points"]["no_transform"] == 11 and fr["bag:/top/points"]["no_transform"] == 13
    assert stats["frames"]["transforms_in"] == 81 + 2 and src["transport_transforms"] == 83
    assert stats["transform_messages"] == 82


def test_static_extrinsics_from_config_and_deskew_through_the_pipeline(tmp_path):
    path, expected, _ = _bag(tmp_path, "mcap", static_in_bag=False, deskew_field="t")
    static = [{"parent": "base_link", "child": ch, "translation": list(map(float, t)),
               "quaternion": list(T.matrix_to_quat(R))} for ch, (R, t) in EXTS.items()]
    stats, snap, _ = _run(path, {"fixed": "odom", "tf_wait_ms": 2000, "static": static}, expected)
    got = snap.positions[np.argsort(snap.channels["intensity"], kind="stable")]
    err = np.linalg.norm(got - np.concatenate(expected), axis=1)
    assert err.max() <= 1e-3
    assert stats["frames"]["sources"]["bag:/left/points"]["deskew"].startswith("Ouster t")


def test_frames_absent_the_bag_replays_as_sent(tmp_path):
    path, expected, _ = _bag(tmp_path, "ros1", n=50)
    cfg_stats, snap, _ = _run(path, {}, [np.zeros((50, 3))] * 30)
    assert cfg_stats["drops"] == {} and "frames" not in cfg_stats and cfg_stats["transform_messages"] == 82
    assert np.abs(snap.positions).max() <= 30.0  # sensor coordinates, untouched
