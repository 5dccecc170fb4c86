"""An independent pose model for the frames tests, written with rotation matrices and
axis-angle (Rodrigues, matrix log) where production uses quaternions and slerp: a moving
robot on an arc, /tf at 20 Hz, and the expected fixed-frame points."""
from __future__ import annotations

import math

import numpy as np

SEC = 1_000_000_000


def rot_z(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_y(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_x(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def hat(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def expm_so3(w):
    th = float(np.linalg.norm(w))
    if th < 1e-15:
        return np.eye(3)
    K = hat(np.asarray(w) / th)
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K


def logm_so3(R):
    c = (np.trace(R) - 1) / 2
    th = math.acos(max(-1.0, min(1.0, c)))
    if th < 1e-12:
        return np.zeros(3)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return v * th / (2 * math.sin(th))


def matrix_to_quat(R):
    """(x, y, z, w) of a rotation matrix (Shepperd), for writing messages only."""
    tr = np.trace(R)
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        w, x, y, z = 0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        w, x, y, z = (R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s
    elif R[1, 1] > R[2, 2]:
        s = math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        w, x, y, z = (R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s
    else:
        s = math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        w, x, y, z = (R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s
    return (x, y, z, w)


class Robot:
    """odom -> base_link: driving an arc (speed m/s, yaw rate rad/s) with some roll wobble;
    /tf sampled every ``tf_dt_ns`` from ``t0``. Between samples the truth is what tf2
    defines: translation linear, rotation along the geodesic (R0 expm(a logm(R0^T R1)))."""

    def __init__(self, t0=1_700_000_000 * SEC, speed=10.0, yaw_rate=0.6, tf_dt_ns=SEC // 20, n_tf=80):
        self.t0, self.speed, self.yaw_rate, self.tf_dt = t0, speed, yaw_rate, tf_dt_ns
        self.stamps = [t0 + k * tf_dt_ns for k in range(n_tf)]

    def sample(self, t_ns):
        """The pose at a sample time (the robot's own continuous motion)."""
        s = (t_ns - self.t0) / SEC
        yaw = self.yaw_rate * s
        r = self.speed / self.yaw_rate
        pos = np.array([r * math.sin(yaw) + 100.0, r * (1 - math.cos(yaw)) - 50.0, 0.2 * math.sin(3 * s)])
        R = rot_z(yaw) @ rot_x(0.05 * math.sin(5 * s)) @ rot_y(0.02 * math.cos(4 * s))
        return R, pos

    def tf(self):
        """[(stamp, R, t)] of odom <- base_link."""
        return [(t,) + self.sample(t) for t in self.stamps]

    def pose(self, t_ns):
        """odom <- base_link at any time within the samples, by the tf2 rule, with matrices."""
        st = self.stamps
        if not st[0] <= t_ns <= st[-1]:
            raise ValueError("outside the samples")
        k = min(int((t_ns - st[0]) // self.tf_dt), len(st) - 2)
        a = (t_ns - st[k]) / (st[k + 1] - st[k])
        R0, p0 = self.sample(st[k])
        R1, p1 = self.sample(st[k + 1])
        R = R0 @ expm_so3(a * logm_so3(R0.T @ R1))
        return R, p0 + a * (p1 - p0)


def extrinsic(translation, rpy_deg=None, R=None):
    if R is None:
        r, p, y = (math.radians(v) for v in rpy_deg)
        R = rot_z(y) @ rot_y(p) @ rot_x(r)
    return R, np.asarray(translation, float)


def to_fixed(robot: Robot, ext, points, t_ns):
    """odom points of sensor points (N,3) captured at t_ns (scalar or (N,) per point)."""
    Re, te = ext
    body = points @ Re.T + te
    t_arr = np.broadcast_to(np.asarray(t_ns), (points.shape[0],))
    out = np.empty_like(body)
    for tv in np.unique(t_arr):
        m = t_arr == tv
        R, p = robot.pose(int(tv))
        out[m] = body[m] @ R.T + p
    return out
