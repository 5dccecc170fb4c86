"""ROS data in: PointCloud2 decode throughput and bag replay through a full pipeline.

1. Decode: an Ouster-like PointCloud2 (131,072 points, 48-byte ``point_step`` with padding:
   x y z float32, 4 pad bytes, intensity float32, t uint32, reflectivity/ring/ambient uint16,
   range uint32, 12 trailing pad bytes) decoded by ``pointflow.ingest.pointcloud2`` against
   the floor: a bare numpy structured view of the same bytes with a prebuilt dtype, copying
   out the same arrays (positions (N, 3) and every channel) and nothing else. Both start
   from the deserialised rosbags message; interleaved repeats, medians; the ratio is
   floor time / decoder time (1.0 = as fast as the floor). The xyz-only variant is the
   same with ``channels: []``.
2. Replay: a ROS 2 MCAP bag of such messages (written here with rosbags) replayed by the
   ``rosbag`` transport (``rate: 0``) through a full pipeline (source, ingest, ring,
   cadence, cpu render) against the same points replayed from a ``.npy`` by the file
   transport in chunks of the same size (the pipeline without ROS), interleaved. Each is run
   looping over its recording until ingest has taken a sixth of ``--points``, then in another
   run all of them; (extra points) / (extra seconds) is the replay rate with startup and
   shutdown cancelled. Also reported: the share of that time the source spends in the
   decoder and in rosbags' deserialiser (their cost per point, measured in the source,
   times the rate).

    .venv/bin/python bench/bench_ros.py [--repeats 5] [--messages 16] [--points 60e6]

Prints a table and writes ``bench/results/ros.json`` and ``ros.png``. Real Ouster xyz/reflectivity/range from
``../shared/data/ouster_os1_128`` are used when that folder exists (else random values).
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import shutil
import statistics
import tempfile
import time

import numpy as np

import _harness as H

ROOT = str(H.ROOT)
DATA = str(H.DATA / "ouster_os1_128")
N = 131_072
STEP = 48
FIELDS = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 16, 7), ("t", 20, 6), ("reflectivity", 24, 4),
          ("ring", 26, 4), ("ambient", 28, 4), ("range", 32, 6)]
CODES = {4: "<u2", 6: "<u4", 7: "<f4"}


def ouster_bytes(seed: int = 0) -> tuple[bytes, str]:
    """131,072 Ouster-like points packed at 48 bytes (padding = 0xAB)."""
    rng = np.random.default_rng(seed)
    rec = np.zeros(N, dtype={"names": [f[0] for f in FIELDS], "formats": [CODES[f[2]] for f in FIELDS],
                             "offsets": [f[1] for f in FIELDS], "itemsize": STEP})
    src = "random"
    files = sorted(glob.glob(os.path.join(DATA, "*.npz")))
    if files:
        with np.load(files[seed % len(files)]) as z:
            xyz, refl, rng_mm = z["xyz"], z["reflectivity"], z["range"]
        m = min(N, xyz.shape[0])
        rec["x"][:m], rec["y"][:m], rec["z"][:m] = xyz[:m, 0], xyz[:m, 1], xyz[:m, 2]
        rec["x"][m:] = np.nan  # dropped beams of an organised scan
        rec["reflectivity"][:m] = refl[:m]
        rec["range"][:m] = rng_mm[:m]
        src = os.path.relpath(files[seed % len(files)], ROOT)
    else:
        rec["x"], rec["y"], rec["z"] = (rng.uniform(-100, 100, N).astype(np.float32) for _ in range(3))
        rec["reflectivity"] = rng.integers(0, 65535, N)
        rec["range"] = rng.integers(0, 1 << 20, N)
    rec["intensity"] = rng.uniform(0, 4000, N).astype(np.float32)
    rec["t"] = np.arange(N, dtype=np.uint32) * 48
    rec["ring"] = np.arange(N) % 128
    rec["ambient"] = rng.integers(0, 65535, N)
    raw = bytearray(rec.tobytes())
    pad = np.frombuffer(raw, np.uint8).reshape(N, STEP)
    pad[:, 12:16] = 0xAB
    pad[:, 36:] = 0xAB
    return bytes(raw), src


def ros_message(data: bytes, stamp_s: int = 1700000000):
    """The deserialised rosbags message (what the rosbag transport hands the decoder)."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    msg = T["sensor_msgs/msg/PointCloud2"](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=stamp_s, nanosec=0), frame_id="os"),
        height=128, width=1024,
        fields=[T["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=d, count=1) for n, o, d in FIELDS],
        is_bigendian=False, point_step=STEP, row_step=STEP * 1024, data=np.frombuffer(data, np.uint8), is_dense=False)
    return ts, msg


def floor_decode(msg, dtype, xyz_dtype, names):
    """The floor: a prebuilt structured view of the bytes, the same arrays copied out."""
    buf = msg.data
    pos = np.ascontiguousarray(np.frombuffer(buf, dtype=xyz_dtype)["xyz"])
    rec = np.frombuffer(buf, dtype=dtype)
    return pos, {n: np.ascontiguousarray(rec[n]) for n in names}


def bench_decode(repeats: int, inner: int) -> dict:
    from pointflow.ingest.pointcloud2 import PointCloud2Decoder

    data, src = ouster_bytes()
    ts, msg = ros_message(data)
    names = [f[0] for f in FIELDS if f[0] not in "xyz"]
    dtype = np.dtype({"names": [f[0] for f in FIELDS], "formats": [CODES[f[2]] for f in FIELDS],
                      "offsets": [f[1] for f in FIELDS], "itemsize": STEP})
    xyz_dtype = np.dtype({"names": ["xyz"], "formats": [("<f4", (3,))], "offsets": [0], "itemsize": STEP})
    raw = ts.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2")
    # the decoder's result must equal the floor's
    c = PointCloud2Decoder().decode(msg)
    fp, fc = floor_decode(msg, dtype, xyz_dtype, names)
    assert np.array_equal(c.positions, fp, equal_nan=True) and all(np.array_equal(c.channels[n], fc[n]) for n in names)

    def timed(fn) -> float:
        t0 = time.perf_counter()
        for _ in range(inner):
            fn()
        return (time.perf_counter() - t0) / inner

    runs = {
        "floor_all": lambda: floor_decode(msg, dtype, xyz_dtype, names),
        "decoder_all": lambda: PointCloud2Decoder().decode(msg),  # layout plan built every time
        "decoder_all_cached": (lambda d=PointCloud2Decoder(): d.decode(msg)),
        "floor_xyz": lambda: floor_decode(msg, dtype, xyz_dtype, []),
        "decoder_xyz": (lambda d=PointCloud2Decoder(channels=[]): d.decode(msg)),
        "rosbags_deserialize_cdr": lambda: ts.deserialize_cdr(raw, "sensor_msgs/msg/PointCloud2"),
    }
    for fn in runs.values():  # warm-up
        fn()
    samples: dict[str, list[float]] = {k: [] for k in runs}
    for _ in range(repeats):  # interleaved: machine load hits every variant alike
        for k, fn in runs.items():
            samples[k].append(timed(fn))
    med = {k: statistics.median(v) for k, v in samples.items()}
    out = {"points": N, "point_step": STEP, "data": src, "inner": inner, "repeats": repeats,
           "ms_per_message": {k: round(v * 1e3, 3) for k, v in med.items()},
           "mpoints_per_s": {k: round(N / v / 1e6, 1) for k, v in med.items() if not k.startswith("rosbags")},
           "ratio_all_vs_floor": round(med["floor_all"] / med["decoder_all"], 3),
           "ratio_all_cached_vs_floor": round(med["floor_all"] / med["decoder_all_cached"], 3),
           "ratio_xyz_vs_floor": round(med["floor_xyz"] / med["decoder_xyz"], 3),
           "samples_ms": {k: [round(x * 1e3, 3) for x in v] for k, v in samples.items()}}
    return out


def write_bag(folder: str, messages: int) -> int:
    from pathlib import Path

    from rosbags.rosbag2 import StoragePlugin, Writer

    total = 0
    with Writer(Path(folder), version=9, storage_plugin=StoragePlugin.MCAP) as w:
        ts = None
        conn = None
        for k in range(messages):
            data, _ = ouster_bytes(k)
            ts, msg = ros_message(data, 1700000000 + k)
            if conn is None:
                conn = w.add_connection("/ouster/points", "sensor_msgs/msg/PointCloud2", typestore=ts)
            w.write(conn, (1700000000 + k) * 10**9 // 10, ts.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))
            total += N
    return total


def run_pipeline(source: dict, total: int) -> dict:
    """Seconds from pipeline start until ingest has taken ``total`` points (startup included;
    the source loops over its recording), and the source's counters."""
    from pointflow import Pipeline

    cfg = {"source": source, "ring": {"max_points": 2_000_000}, "tracing": {"enabled": False},
           # stats every 50 ms (fine timing); a stage starved for a while on a shared machine is not hung
           "supervisor": {"heartbeat_ms": 50, "hung_after_ms": 5000},
           "render": {"backend": "cpu", "size": [320, 240], "color_by": "intensity", "output": {"dir": None}}}
    t0 = time.perf_counter()
    with Pipeline.from_dict(cfg) as p:
        p.wait(300, until=lambda: p.stats()["stages"].get("ingest", {}).get("points_in", 0) >= total)
        t1 = time.perf_counter()
        st = p.stats()["stages"]
    src = st.get("source", {})
    return {"seconds": t1 - t0, "decode_s": src.get("transport_decode_s", 0.0),
            "deserialize_s": src.get("transport_deserialize_s", 0.0), "decoded_points": src.get("transport_points", 0)}


def transport_alone(source: dict, points: int) -> float:
    """points/s of the transport by itself in this process (read, deserialise, decode; no
    pipeline): the ceiling a replay could reach if ingest and the ring cost nothing."""
    from pointflow.ingest.transports import resolve_transport

    cls = resolve_transport(source["transport"])
    t = cls(cls.validate_options(source["options"], "bench", ROOT), "bench")
    t.open()
    try:
        n = 0
        t0 = time.perf_counter()
        for c in t.chunks():
            if c is not None:
                n += c.n
                if n >= points:
                    break
        return n / (time.perf_counter() - t0)
    finally:
        t.close()


def bench_replay(repeats: int, messages: int, small_points: int, large_points: int) -> dict:
    """Differential: each source replays its recording in a loop until ingest has taken
    ``small_points`` and, in another run, ``large_points``; the extra points over the extra
    seconds is the replay rate with startup and shutdown cancelled. The decoder's share of
    that time is its own cost per point (measured in the source) x that rate."""
    tmp = tempfile.mkdtemp(prefix="pointflow-bench-ros-")
    try:
        bag = os.path.join(tmp, "ouster_bag")
        write_bag(bag, messages)
        # the same points as a .npy for the file transport, one scan per chunk
        arr = np.concatenate([np.frombuffer(ouster_bytes(k)[0], np.uint8).reshape(N, STEP)[:, :20].copy()
                              .view("<f4").reshape(N, 5)[:, [0, 1, 2, 4]] for k in range(messages)])
        npy = os.path.join(tmp, "same_points.npy")
        np.save(npy, arr)
        bag_opts = {"path": bag, "rate": 0, "progress": "off", "loop": True}
        srcs = {"rosbag": {"transport": "rosbag", "options": bag_opts},
                # the payload of the .npy path: positions + intensity only
                "rosbag_intensity": {"transport": "rosbag", "options": {**bag_opts, "channels": ["intensity"]}},
                "file_npy": {"transport": "file", "options": {"path": npy, "realtime": False, "mode": "stream",
                                                              "chunk_points": N, "progress": "off", "loop": True}}}
        runs: dict[str, list[dict]] = {k: [] for k in srcs}
        alone: dict[str, list[float]] = {k: [] for k in srcs}
        for _ in range(repeats):  # interleaved
            for k, src in srcs.items():
                alone[k].append(transport_alone(src, small_points))
                a = run_pipeline(src, small_points)
                b = run_pipeline(src, large_points)
                dt = b["seconds"] - a["seconds"]
                rate = (large_points - small_points) / dt if dt > 0 else None
                row = {"seconds_small": round(a["seconds"], 3), "seconds_large": round(b["seconds"], 3),
                       "points_per_s": round(rate) if rate else None}
                if k.startswith("rosbag") and rate and b["decoded_points"]:
                    row["decode_ns_per_point"] = round(b["decode_s"] / b["decoded_points"] * 1e9, 3)
                    row["decode_share"] = round(b["decode_s"] / b["decoded_points"] * rate, 4)
                    row["deserialize_share"] = round(b["deserialize_s"] / b["decoded_points"] * rate, 4)
                runs[k].append(row)
        med = {k: statistics.median(r["points_per_s"] for r in v if r["points_per_s"]) for k, v in runs.items()}

        def share(k, key):
            return statistics.median(r[key] for r in runs[k] if r.get(key) is not None)

        return {"messages_in_recording": messages, "points_per_message": N, "points": [small_points, large_points],
                "repeats": repeats, "points_per_s": {k: round(v) for k, v in med.items()},
                "transport_alone_points_per_s": {k: round(statistics.median(v)) for k, v in alone.items()},
                "vs_file_npy": {k: round(v / med["file_npy"], 3) for k, v in med.items()},
                "decode_share_of_replay": {k: share(k, "decode_share") for k in runs if k.startswith("rosbag")},
                "deserialize_share_of_replay": {k: share(k, "deserialize_share") for k in runs if k.startswith("rosbag")},
                "runs": runs}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def plot(res: dict, path: str) -> None:
    """bench/results/ros.png: decode vs floor, replay rates (matplotlib, the plot extra)."""
    if (plt := H.pyplot()) is None:
        return
    d = res["decode"]["mpoints_per_s"]
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.6))
    names = ["floor_all", "decoder_all", "floor_xyz", "decoder_xyz"]
    a.bar(range(4), [d[k] for k in names], color=["#999", "#3b7", "#999", "#3b7"])
    a.set_xticks(range(4), ["floor\nxyz+6 ch", "decoder\nxyz+6 ch", "floor\nxyz", "decoder\nxyz"])
    a.set_ylabel("Mpoints/s")
    a.set_title(f"PointCloud2 decode, {N:,} pts x {STEP} B")
    if "replay" in res:
        r = res["replay"]
        ks = list(r["points_per_s"])
        x = np.arange(len(ks))
        b.bar(x - 0.2, [r["points_per_s"][k] / 1e6 for k in ks], 0.4, label="full pipeline", color="#37b")
        b.bar(x + 0.2, [r["transport_alone_points_per_s"][k] / 1e6 for k in ks], 0.4, label="transport alone",
              color="#bbb")
        b.set_xticks(x, [k.replace("_", "\n") for k in ks])
        b.set_ylabel("Mpoints/s")
        b.set_title("replay (shared 2-core VM)")
        b.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--inner", type=int, default=20, help="decodes per timed sample")
    ap.add_argument("--messages", type=int, default=16, help="messages in the replayed bag (replayed in a loop)")
    ap.add_argument("--points", type=float, default=60e6, help="points replayed in the long run (the short run: a sixth)")
    ap.add_argument("--skip-replay", action="store_true")
    ap.add_argument("--plot-only", action="store_true", help="redraw ros.png from ros.json")
    args = ap.parse_args()
    out_dir = str(H.RESULTS)
    if args.plot_only:
        with open(os.path.join(out_dir, "ros.json")) as f:
            plot(json.load(f), os.path.join(out_dir, "ros.png"))
        return
    res = {"machine": H.machine(numpy=np.__version__), "command": H.command()}
    res["decode"] = d = bench_decode(args.repeats, args.inner)
    print(f"decode, {N:,} points x {STEP} B ({d['data']}): ms/message (median of {args.repeats})")
    for k, v in d["ms_per_message"].items():
        mp = d["mpoints_per_s"].get(k)
        print(f"  {k:26s} {v:8.3f} ms" + (f"  {mp:7.1f} Mpoints/s" if mp else ""))
    print(f"  decoder / floor throughput: all channels {d['ratio_all_vs_floor']:.2f} "
          f"(plan cached {d['ratio_all_cached_vs_floor']:.2f}), xyz only {d['ratio_xyz_vs_floor']:.2f}  (target >= 0.50)")
    if not args.skip_replay:
        res["replay"] = r = bench_replay(max(1, args.repeats // 2 + 1), args.messages, int(args.points) // 6, int(args.points))
        print(f"replay through a full pipeline, {r['points'][1]:,} vs {r['points'][0]:,} points, a recording of "
              f"{r['messages_in_recording']} scans looped (differential, median of {r['repeats']}):")
        for k, v in r["points_per_s"].items():
            line = (f"  {k:18s} {v / 1e6:6.2f} Mpoints/s  ({r['vs_file_npy'][k]:.2f} x file .npy; transport alone "
                    f"{r['transport_alone_points_per_s'][k] / 1e6:6.2f})")
            if k in r["decode_share_of_replay"]:
                line += (f"  time in decoder {r['decode_share_of_replay'][k] * 100:.1f}%, "
                         f"in rosbags' deserialiser {r['deserialize_share_of_replay'][k] * 100:.1f}%")
            print(line)
    H.machine_done(res["machine"])
    H.write_result(os.path.join(out_dir, "ros.json"), res)
    plot(res, os.path.join(out_dir, "ros.png"))


if __name__ == "__main__":
    main()
