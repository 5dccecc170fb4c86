"""Frames at ingest: cost of placing a cloud in the fixed frame, of deskew, and what each buys.

Three measurements, each against a baseline taken in the same run (interleaved, medians):

* ``transform``: the frames step (``Framer.submit``: chain lookup at the cloud's stamp, lerp +
  slerp of the dynamic edge, composition, then the points) on a 131,072-point float64 cloud,
  against the floor ``points @ R.T + t`` in bare numpy on the same array. Target >= 0.7
  (floor time / our time).
* ``deskew``: the same cloud with Ouster per-point times (``t`` uint32, 1024 column times):
  each point with the pose at its own time. Target >= 0.3 of the same floor. Also
  ``deskew_continuous``: the times made distinct per point (as Velodyne or Hesai stamp them),
  which takes deskew's node-interpolation path instead of one pose per distinct time.
* ``pipeline``: the real ingest stage in its own process fed by a producer process over
  ZeroMQ (10,000- and 1,000-point chunks) with ``frames.fixed`` set (static chain, every
  chunk transformed) against the same without ``frames``. Target >= 0.85.

And the error-versus-cost chart: a real Ouster OS-1-128 scan (``../shared/data``, when
present; else a synthetic sweep) taken by a lidar on a robot driving an arc (10 m/s, 0.6
rad/s, roll/pitch wobble; /tf at 20 Hz), placed as sent, with one transform per cloud (at
the header stamp, the start of the sweep), and deskewed; error = distance to where each point
truly was (the continuous motion, not the 20 Hz samples), median and max, next to the cost
per cloud.

    .venv/bin/python bench/bench_frames.py [--reps 31] [--pipeline-points 3000000] [--rounds 3]

Writes ``bench/results/frames.json`` and ``bench/results/frames.png``.
"""
from __future__ import annotations

import argparse
import glob
import json
import math
import os
import statistics
import time

import numpy as np

import _harness as H
from _harness.ingest import FRAMES_ON, IngestRun

DATA = str(H.DATA / "ouster_os1_128")
N = 131_072
SEC = 1_000_000_000
T0 = 1_700_000_000 * SEC


# ----------------------------------------------------------------------------- motion
def _rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _rx(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def pose(t_ns: float):
    """odom <- base_link of a robot driving an arc, starting at odom's origin at T0."""
    s = (t_ns - T0) / SEC
    speed, yaw_rate = 10.0, 0.6
    yaw = yaw_rate * s
    r = speed / yaw_rate
    p = np.array([r * math.sin(yaw), r * (1 - math.cos(yaw)), 0.05 * math.sin(3 * s)])
    return _rz(yaw) @ _rx(0.03 * math.sin(5 * s)), p


def _quat(R):
    from pointflow.frames.rotation import from_matrix

    return tuple(from_matrix(R))


def framer(deskew="auto"):
    from pointflow.frames.config import FramesConfig
    from pointflow.frames.framer import Framer
    from pointflow.frames.message import Transform, Transforms

    fr = Framer(FramesConfig(fixed="odom", deskew=deskew), lambda r, n: None)
    tfs = [Transform("base_link", "lidar", 0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), True)]
    for k in range(-10, 40):  # /tf at 20 Hz around the sweep
        st = T0 + k * SEC // 20
        R, p = pose(st)
        tfs.append(Transform("odom", "base_link", st, tuple(p), _quat(R)))
    fr.add_transforms(Transforms(tfs, "bench"))
    return fr


def ouster_scan():
    """(xyz float32 (N,3) sensor frame, per-point t uint32 ns after the first column, label)."""
    files = sorted(glob.glob(os.path.join(DATA, "*.npz")))
    if files:
        with np.load(files[0]) as z:
            xyz = z["xyz"].astype(np.float32)
            ts = z["timestamps_ns"].astype(np.int64)
        # the columns sweep the azimuth once: a point's column (so its time) from its azimuth
        az = np.mod(-np.arctan2(xyz[:, 1], xyz[:, 0]) + math.atan2(xyz[0, 1], xyz[0, 0]), 2 * np.pi)
        col = np.minimum((az / (2 * np.pi) * ts.size).astype(np.intp), ts.size - 1)
        return xyz, (ts[col] - ts[0]).astype(np.uint32), f"Ouster OS-1-128 scan ({xyz.shape[0]:,} points, {os.path.basename(files[0])})"
    rng = np.random.default_rng(0)
    az = rng.uniform(0, 2 * np.pi, 107_000)
    r = rng.uniform(2, 80, az.size)
    xyz = np.column_stack([r * np.cos(az), r * np.sin(az), rng.uniform(-2, 8, az.size)]).astype(np.float32)
    col = (az / (2 * np.pi) * 1024).astype(np.int64)
    return xyz, (col * 97_656).astype(np.uint32), "synthetic sweep (no ../shared/data)"


def chunk(pos, t=None, stamp=T0 + 3 * SEC // 100):
    from pointflow.chunk import PointChunk

    return PointChunk(positions=pos, channels={} if t is None else {"t": t}, source_id="bench", stamp_ns=stamp,
                      frame_id="lidar", trace_id=0)


# ----------------------------------------------------------------------------- micro
def micro(reps: int) -> dict:
    xyz, t, label = ouster_scan()
    idx = np.resize(np.arange(xyz.shape[0]), N)  # 131,072 points: the scan, repeated
    pts = np.ascontiguousarray(xyz[idx].astype(np.float64))
    tt = np.ascontiguousarray(t[idx])
    # the same times made continuous (each point its own time, as Velodyne/Hesai stamp them):
    # too many distinct values for one pose each, so deskew interpolates between pose nodes
    tc = tt + (np.arange(N) % 97).astype(np.uint32) * 811
    fr_rigid, fr_desk, fr_cont = framer("off"), framer("auto"), framer("auto")
    c_rigid, c_desk, c_cont = chunk(pts), chunk(pts, tt), chunk(pts, tc)
    R, tr = fr_rigid.buffer.lookup("odom", "lidar", c_rigid.stamp_ns)
    times = {"floor": [], "transform": [], "deskew": [], "deskew_continuous": []}
    for _ in range(3):  # warm-up
        _ = pts @ R.T + tr
        fr_rigid.submit(c_rigid, pts, {})
        fr_desk.submit(c_desk, pts, {})
        fr_cont.submit(c_cont, pts, {})
    for _ in range(reps):  # interleaved: the machine's load hits all alike
        a = time.perf_counter(); _ = pts @ R.T + tr; b = time.perf_counter()
        out_r = fr_rigid.submit(c_rigid, pts, {}); c = time.perf_counter()
        out_d = fr_desk.submit(c_desk, pts, {}); d = time.perf_counter()
        fr_cont.submit(c_cont, pts, {}); e = time.perf_counter()
        times["floor"].append(b - a)
        times["transform"].append(c - b)
        times["deskew"].append(d - c)
        times["deskew_continuous"].append(e - d)
    assert np.allclose(out_r[0][1], pts @ R.T + tr)
    Rp, tp = fr_desk.buffer.lookup_many("odom", "lidar", c_desk.stamp_ns + tt.astype(np.int64))
    assert np.abs(out_d[0][1] - (np.einsum("nij,nj->ni", Rp, pts) + tp)).max() < 1e-9
    med = {k: statistics.median(v) for k, v in times.items()}
    return {"points": N, "data": label, "reps": reps, "load_avg_1min": os.getloadavg()[0],
            "median_ms": {k: round(v * 1e3, 3) for k, v in med.items()},
            "transform_vs_floor": round(med["floor"] / med["transform"], 3),
            "deskew_vs_floor": round(med["floor"] / med["deskew"], 3),
            "deskew_continuous_vs_floor": round(med["floor"] / med["deskew_continuous"], 3),
            "targets": {"transform_vs_floor": 0.7, "deskew_vs_floor": 0.3}}


# ----------------------------------------------------------------------------- error vs cost
def error_vs_cost(reps: int) -> dict:
    xyz, t, label = ouster_scan()
    pts = xyz.astype(np.float64)
    stamp = T0 + 3 * SEC // 100  # header stamp = first column, between two /tf samples
    times = stamp + t.astype(np.int64)
    truth = np.empty_like(pts)
    for tv in np.unique(times):  # where each point truly was: the continuous motion
        m = times == tv
        Rm, pm = pose(float(tv))
        truth[m] = pts[m] @ Rm.T + pm
    fr_rigid, fr_desk = framer("off"), framer("auto")
    out = {"as sent": (pts, [0.0]), "per-cloud transform": None, "deskew": None}
    cost = {"per-cloud transform": [], "deskew": []}
    for _ in range(reps):
        a = time.perf_counter(); r = fr_rigid.submit(chunk(xyz, stamp=stamp), xyz, {}); b = time.perf_counter()
        d = fr_desk.submit(chunk(xyz, t, stamp=stamp), xyz, {}); c = time.perf_counter()
        cost["per-cloud transform"].append(b - a)
        cost["deskew"].append(c - b)
    out["per-cloud transform"] = (r[0][1], cost["per-cloud transform"])
    out["deskew"] = (d[0][1], cost["deskew"])
    # tf2's own answer per point (exact lerp + slerp at each point's time): what deskew approximates
    Rp, tp = fr_desk.buffer.lookup_many("odom", "lidar", times)
    exact_tf2 = np.einsum("nij,nj->ni", Rp, pts) + tp
    desk_vs_tf2 = np.linalg.norm(out["deskew"][0] - exact_tf2, axis=1)
    # continuous per-point times (each point its own): the node-interpolation path, against tf2
    tc = t + (np.arange(t.shape[0]) % 97).astype(np.uint32) * 811
    dc = framer("auto").submit(chunk(xyz, tc, stamp=stamp), xyz, {})[0][1]
    Rc, tcp = fr_desk.buffer.lookup_many("odom", "lidar", stamp + tc.astype(np.int64))
    nodes_vs_tf2 = np.linalg.norm(dc - (np.einsum("nij,nj->ni", Rc, pts) + tcp), axis=1)
    res = {"data": label, "points": int(pts.shape[0]), "motion": "arc 10 m/s, 0.6 rad/s yaw, roll wobble; /tf 20 Hz",
           "deskew_vs_exact_tf2_per_point_m": {"median": float(np.median(desk_vs_tf2)), "max": float(desk_vs_tf2.max())},
           "deskew_continuous_times_vs_exact_tf2_per_point_m": {"median": float(np.median(nodes_vs_tf2)),
                                                                 "max": float(nodes_vs_tf2.max())},
           "sweep_ms": round(float(t.max()) / 1e6, 2), "modes": {}}
    for k, (p, c) in out.items():
        e = np.linalg.norm(p - truth, axis=1)
        res["modes"][k] = {"error_median_m": float(np.median(e)), "error_max_m": float(e.max()),
                           "cost_ms_per_cloud": round(statistics.median(c) * 1e3, 3)}
    return res


# ----------------------------------------------------------------------------- pipeline
def pipeline(points: int, rounds: int) -> dict:
    out = {}
    for n in (10_000, 1_000):
        count = max(1, points // n)
        rates = {"off": [], "on": []}
        cpu = {"off": [], "on": []}
        runs = {"off": IngestRun(2_000_000, None), "on": IngestRun(2_000_000, FRAMES_ON)}
        try:
            for i in range(rounds):  # interleaved, alternating which goes first
                for k in H.order(("off", "on"), i):
                    runs[k].measure(n, count, "lidar", stamp0=T0)
                    rates[k].append(runs[k].hb_rate)  # until the heartbeat that shows every point
                    cpu[k].append(runs[k].cpu_rate)
        finally:
            finals = {k: r.close() for k, r in runs.items()}
        assert finals["on"].get("frames", {}).get("sources", {}).get("bench", {}).get("chain") == "odom <- lidar"
        med = {k: statistics.median(v) for k, v in rates.items()}
        cmed = {k: statistics.median(v) for k, v in cpu.items()}
        out[f"{n}_points_per_chunk"] = {"points_per_s_median": {k: round(v) for k, v in med.items()},
                                         "rounds": {k: [round(x) for x in v] for k, v in rates.items()},
                                         "on_vs_off": round(med["on"] / med["off"], 3), "target": 0.85,
                                         "on_vs_off_each_round": [round(a / b, 3) for a, b in zip(rates["on"], rates["off"])],
                                         "ingest_points_per_cpu_s_median": {k: round(v) for k, v in cmed.items()},
                                         "cpu_on_vs_off": round(cmed["on"] / cmed["off"], 3),
                                         "load_avg_1min": os.getloadavg()[0]}
    return out


# ----------------------------------------------------------------------------- chart
def chart(res: dict, path: str) -> None:
    if (plt := H.pyplot()) is None:
        return

    ev = res["error_vs_cost"]
    fig, ax = plt.subplots(figsize=(7.5, 4.6))
    colors = {"as sent": "#999999", "per-cloud transform": "#1f77b4", "deskew": "#d62728"}
    for k, m in ev["modes"].items():
        x = max(m["cost_ms_per_cloud"], 0.05)
        ax.errorbar([x], [m["error_median_m"]], yerr=[[0], [m["error_max_m"] - m["error_median_m"]]], fmt="o",
                    color=colors[k], capsize=5, ms=8, label=f"{k}: median {m['error_median_m'] * 1000:.3g} mm, "
                    f"max {m['error_max_m'] * 1000:.3g} mm, {m['cost_ms_per_cloud']:.2f} ms")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.axhline(1e-3, color="k", lw=0.6, ls=":")
    ax.text(0.06, 1.15e-3, "1 mm", fontsize=8)
    ax.set_xlabel("cost per cloud at ingest, ms (as sent: none, drawn at 0.05)")
    ax.set_ylabel("distance to true position, m (dot: median, bar: max)")
    ax.set_title(f"Sweep error vs cost: {ev['data'][:48]}\n{ev['motion']}", fontsize=9)
    ax.legend(fontsize=7.5, loc="lower left")
    ax.grid(True, which="both", alpha=0.3)
    fig.text(0.99, 0.01, f"{H.machine_line(res['machine'])}, numpy {np.__version__}", ha="right", fontsize=6.5,
             color="#555")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=31)
    ap.add_argument("--pipeline-points", type=int, default=3_000_000)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--skip-pipeline", action="store_true")
    ap.add_argument("--out", default=str(H.RESULTS / "frames.json"))
    a = ap.parse_args()
    res = {"machine": H.machine(numpy=np.__version__), "command": H.command(),
           "openblas_threads": os.environ.get("OPENBLAS_NUM_THREADS", "default")}
    res["micro"] = micro(a.reps)
    print(json.dumps(res["micro"], indent=1))
    res["error_vs_cost"] = error_vs_cost(max(5, a.reps // 3))
    print(json.dumps(res["error_vs_cost"], indent=1))
    if not a.skip_pipeline:
        res["pipeline"] = pipeline(a.pipeline_points, a.rounds)
        print(json.dumps(res["pipeline"], indent=1))
    H.machine_done(res["machine"])
    H.write_result(a.out, res, indent=1)
    chart(res, os.path.splitext(a.out)[0] + ".png")


if __name__ == "__main__":
    main()
