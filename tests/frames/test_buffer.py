"""The transform buffer against the matrix model in truth.py: interpolation between
samples, chains of static and dynamic edges, history, and the tree checks."""
import numpy as np
import pytest

from pointflow.frames.buffer import FrameError, NoTransform, TransformBuffer

from . import truth as T


def _buffer(robot, exts):
    b = TransformBuffer()
    for st, R, p in robot.tf():
        b.set_transform("odom", "base_link", st, p, T.matrix_to_quat(R))
    for child, (R, t) in exts.items():
        b.set_transform("base_link", child, 0, t, T.matrix_to_quat(R), static=True)
    return b


EXTS = {"lidar_top": T.extrinsic([0.9, 0.0, 1.7], [0, 2, 0]),
        "lidar_left": T.extrinsic([0.3, 0.8, 1.2], [10, -5, 90])}


def test_lookup_between_samples_equals_matrix_geodesic():
    robot = T.Robot()
    b = _buffer(robot, EXTS)
    rng = np.random.default_rng(1)
    for t in robot.stamps[0] + rng.integers(0, robot.stamps[-1] - robot.stamps[0], 50):
        for child, ext in EXTS.items():
            R, p = b.lookup("odom", child, int(t))
            Rb, pb = robot.pose(int(t))
            assert np.allclose(R, Rb @ ext[0], atol=1e-12)
            assert np.allclose(p, Rb @ ext[1] + pb, atol=1e-9)


def test_lookup_many_and_inverse_direction():
    robot = T.Robot()
    b = _buffer(robot, EXTS)
    times = np.array(robot.stamps[3:6], np.int64) + 12_345_678
    R, p = b.lookup_many("lidar_left", "lidar_top", times)  # sibling frames via base_link
    for k, t in enumerate(times):
        (Rl, tl), (Rt, tt) = EXTS["lidar_left"], EXTS["lidar_top"]
        assert np.allclose(R[k], Rl.T @ Rt, atol=1e-12)
        assert np.allclose(p[k], Rl.T @ (tt - tl), atol=1e-12)
    R2, p2 = b.lookup("base_link", "odom", int(times[0]))
    Rb, pb = robot.pose(int(times[0]))
    assert np.allclose(R2, Rb.T, atol=1e-12) and np.allclose(p2, -Rb.T @ pb, atol=1e-9)


def test_no_extrapolation_unknown_frames_and_history():
    robot = T.Robot(n_tf=10)
    b = _buffer(robot, EXTS)
    with pytest.raises(NoTransform) as e:
        b.lookup("odom", "lidar_top", robot.stamps[-1] + 1)
    assert e.value.retry and "not extrapolated" in str(e.value) and "odom -> base_link" in str(e.value)
    with pytest.raises(NoTransform) as e:
        b.lookup("odom", "lidar_top", robot.stamps[0] - 1)
    assert not e.value.retry  # before the history: waiting cannot help
    with pytest.raises(NoTransform, match="unknown frame 'camera'") as e:
        b.lookup("odom", "camera", robot.stamps[2])
    assert "the buffer holds" in str(e.value)
    small = TransformBuffer(history_ns=T.SEC // 10)
    for st, R, p in robot.tf():
        small.set_transform("odom", "base_link", st, p, T.matrix_to_quat(R))
    assert len(small.edges["base_link"].stamps) == 3  # newest and 100 ms back (20 Hz)


def test_static_only_chain_and_time_zero_is_newest():
    b = TransformBuffer()
    b.set_transform("map", "odom", 0, [1, 2, 3], [0, 0, 0, 1], static=True)
    b.set_transform("odom", "lidar", 0, [0, 0, 1], T.matrix_to_quat(T.rot_z(np.pi / 2)), static=True)
    R, t = b.lookup("map", "lidar", 123)  # any time: static
    assert np.allclose(R, T.rot_z(np.pi / 2)) and np.allclose(t, [1, 2, 4])
    assert b.chain_text("map", "lidar") == "map <- odom <- lidar"


def test_two_parents_and_loops_are_refused_without_changing_the_tree():
    b = TransformBuffer()
    b.set_transform("odom", "base", 1, [0, 0, 0], [0, 0, 0, 1])
    b.set_transform("base", "lidar", 0, [0, 0, 0], [0, 0, 0, 1], static=True)
    with pytest.raises(FrameError) as e:
        b.set_transform("map", "lidar", 0, [0, 0, 0], [0, 0, 0, 1], static=True)
    assert e.value.reason == "tf_two_parents" and "already has parent 'base'" in str(e.value)
    with pytest.raises(FrameError) as e:
        b.set_transform("lidar", "odom", 1, [0, 0, 0], [0, 0, 0, 1])
    assert e.value.reason == "tf_loop"
    with pytest.raises(FrameError) as e:
        b.set_transform("odom", "odom", 1, [0, 0, 0], [0, 0, 0, 1])
    assert e.value.reason == "tf_loop"
    with pytest.raises(FrameError) as e:
        b.set_transform("odom", "base", 2, [0, 0, np.nan], [0, 0, 0, 1])
    assert e.value.reason == "tf_bad"
    assert {c: e.parent for c, e in b.edges.items()} == {"base": "odom", "lidar": "base"}
    assert b.lookup("odom", "lidar", 1)[1].tolist() == [0, 0, 0]


def test_out_of_order_samples_are_sorted():
    robot = T.Robot(n_tf=6)
    b = TransformBuffer()
    for st, R, p in reversed(robot.tf()):
        b.set_transform("odom", "base_link", st, p, T.matrix_to_quat(R))
    t = robot.stamps[2] + 7_000_000
    R, p = b.lookup("odom", "base_link", t)
    Rb, pb = robot.pose(t)
    assert np.allclose(R, Rb, atol=1e-12) and np.allclose(p, pb, atol=1e-9)
