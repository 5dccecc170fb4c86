"""Ingest throughput: producer process -> ZeroMQ -> ingest process -> shared-memory ring.

For chunks of 1k, 10k and 100k points (float32 xyz + intensity) it measures, in the same
run, three paths and reports points/s (median of ``--repeats``):

* ``pointflow``: the real ingest stage (``stage_main``) in its own process: decode,
  validation, non-finite check, conversion, coalescing, ring push, accounting;
* ``naive``: the same chunks pickled through a ``multiprocessing.Queue`` into a plain
  numpy array in another process;
* ``raw``: the same bytes over ZeroMQ ``copy=False`` into a numpy array, no validation.

Plus end-to-end replay (file transport -> source process -> ingest) of
``../shared/data/autzen_trim.laz`` and the Ouster scans when that folder exists.

    .venv/bin/python bench/bench_ingest.py [--points 10000000] [--repeats 3] [--sizes 1000,10000]

Prints a table, the ratios issue 20 sets targets for (ingest / raw ZeroMQ at 1k and 10k-point
chunks, medians of the repeats) and writes ``bench/results/ingest.json``. Every path is timed
from the start signal to its last point stored (pointflow: the time of the ring push that
completed the count, from the ring's header);
``of_raw_legacy`` keeps the earlier timing (pointflow until a heartbeat shows every point,
raw and naive from their first message), which counted up to a heartbeat interval (10 ms)
against pointflow: 10-15 % of a 10k-chunk run.
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import shutil
import statistics
import time

import numpy as np
import zmq

import _harness as H
from _harness.ingest import FRAMES_ON, IngestRun
from _harness.ingest import chunk as _chunk

DATA = str(H.DATA)
SIZES = (1_000, 10_000, 100_000)


# ----------------------------------------------------------------------------- producers
def _raw_producer(endpoint: str, n: int, count: int, go, ready) -> None:
    pos, inten = _chunk(n, 1)
    ctx = zmq.Context()
    s = ctx.socket(zmq.PUSH)
    s.setsockopt(zmq.SNDHWM, 64)
    s.connect(endpoint)
    ready.set()
    go.wait()
    for _ in range(count):
        s.send_multipart([pos, inten], copy=False)
    s.close(linger=-1)
    ctx.term()


def _raw_consumer(endpoint: str, n: int, count: int, cap: int, out) -> None:
    ctx = zmq.Context()
    s = ctx.socket(zmq.PULL)
    s.bind(endpoint)
    out.put("ready")
    ring_pos = np.empty((cap, 3), np.float32)
    ring_i = np.empty(cap, np.float32)
    head = 0
    t0 = None
    for _ in range(count):
        f = s.recv_multipart(copy=False)
        if t0 is None:
            t0 = time.perf_counter()
        p = np.frombuffer(f[0].buffer, np.float32).reshape(-1, 3)
        it = np.frombuffer(f[1].buffer, np.float32)
        m = p.shape[0]
        if head + m > cap:
            head = 0
        ring_pos[head:head + m] = p
        ring_i[head:head + m] = it
        head += m
    out.put((t0, time.perf_counter()))
    s.close()
    ctx.term()


def _naive_producer(q, n: int, count: int, go, ready) -> None:
    pos, inten = _chunk(n, 1)
    ready.set()
    go.wait()
    for i in range(count):
        q.put({"positions": pos, "intensity": inten, "seq": i})
    q.put(None)


def _naive_consumer(q, cap: int, out) -> None:
    ring_pos = np.empty((cap, 3), np.float32)
    ring_i = np.empty(cap, np.float32)
    head = 0
    t0 = None
    out.put("ready")
    while True:
        c = q.get()
        if t0 is None:
            t0 = time.perf_counter()
        if c is None:
            break
        m = c["positions"].shape[0]
        if head + m > cap:
            head = 0
        ring_pos[head:head + m] = c["positions"]
        ring_i[head:head + m] = c["intensity"]
        head += m
    out.put((t0, time.perf_counter()))


# ----------------------------------------------------------------------------- runs
def run_naive(n: int, count: int, cap: int) -> float:
    ctx = mp.get_context("spawn")
    q, out, go, ready = ctx.Queue(maxsize=64), ctx.Queue(), ctx.Event(), ctx.Event()
    cons = ctx.Process(target=_naive_consumer, args=(q, cap, out), daemon=True)
    prod = ctx.Process(target=_naive_producer, args=(q, n, count, go, ready), daemon=True)
    cons.start(); prod.start()
    out.get(timeout=60)
    ready.wait(60)
    time.sleep(0.1)  # as for the others: both sides started and waiting
    t_go = time.perf_counter()
    go.set()
    t_first, t_end = out.get(timeout=600)
    prod.join(); cons.join()
    return _rates(n * count, t_go, t_first, t_end)


def run_raw(n: int, count: int, cap: int, run_dir: str) -> float:
    ctx = mp.get_context("spawn")
    ep = f"ipc://{run_dir}/raw.sock"
    out, go, ready = ctx.Queue(), ctx.Event(), ctx.Event()
    cons = ctx.Process(target=_raw_consumer, args=(ep, n, count, cap, out), daemon=True)
    cons.start()
    out.get(timeout=60)
    prod = ctx.Process(target=_raw_producer, args=(ep, n, count, go, ready), daemon=True)
    prod.start()
    ready.wait(60)
    time.sleep(0.1)  # as for pointflow: the producer is connected and waiting
    t_go = time.perf_counter()
    go.set()
    t_first, t_end = out.get(timeout=600)
    prod.join(); cons.join()
    return _rates(n * count, t_go, t_first, t_end)


def _rates(points: int, t_go: float, t_first: float, t_end: float) -> tuple[float, float]:
    """(points/s from the start signal to the last point stored, the same from the first
    message received: the way this bench timed naive and raw before; time.perf_counter is
    CLOCK_MONOTONIC, one clock for every process of the machine)."""
    return points / (t_end - t_go), points / (t_end - t_first)


def run_replay(path: str, label: str, extra: dict) -> dict:
    """End to end: file source process -> ingest process -> ring, as fast as ingest takes."""
    from pointflow import Pipeline

    cfg = {"source": {"transport": "file", "options": {"path": path, "realtime": False, "progress": "off", **extra}},
           "ring": {"max_points": 2_000_000}, "tracing": {"enabled": False},
           "render": {"backend": "cpu", "size": [320, 240], "color_by": "intensity", "output": {"dir": None}}}
    from pointflow.ingest.transports.file import _expand
    from pointflow import formats

    total = sum(formats.read(f)[0].shape[0] for f in _expand(path))
    t0 = time.perf_counter()
    with Pipeline.from_dict(cfg) as p:
        p.wait(120, until=lambda: p.stats()["stages"].get("ingest", {}).get("points_out", 0) >= total)
        dt = time.perf_counter() - t0
        st = p.stats()["stages"]
    return {"what": label, "points": total, "seconds_incl_startup": round(dt, 3),
            "points_out": st.get("ingest", {}).get("points_out"), "points_per_s_incl_startup": round(total / dt)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=10_000_000, help="points per measurement")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--sizes", default=",".join(map(str, SIZES)), help="chunk sizes, comma-separated")
    ap.add_argument("--no-replay", action="store_true", help="skip the end-to-end replays")
    ap.add_argument("--no-frames", action="store_true", help="skip the run with frames.fixed set")
    ap.add_argument("--out", default=str(H.RESULTS / "ingest.json"), help="results JSON")
    args = ap.parse_args()
    from pointflow.config import new_run_dir

    cap = 2_000_000
    results = {"machine": H.machine(), "command": H.command(), "rows": [], "replay": []}
    run_dir = new_run_dir()
    ing = IngestRun(cap)
    ing_fr = None if args.no_frames else IngestRun(cap, FRAMES_ON)
    try:
        ing.measure(10_000, 2 * cap // 10_000)  # warm-up: every ring page touched once
        if ing_fr is not None:
            ing_fr.measure(10_000, 2 * cap // 10_000, "lidar")
        for n in (int(x) for x in args.sizes.split(",")):
            count = max(20, args.points // n)
            samples: dict[str, list[float]] = {k: [] for k in ("naive", "raw", "pointflow", "cpu",
                                                               "naive_first", "raw_first", "pointflow_hb")}
            for _ in range(args.repeats):  # interleaved, so machine load hits all three alike
                for k, (go_rate, first_rate) in (("naive", run_naive(n, count, cap)), ("raw", run_raw(n, count, cap, run_dir))):
                    samples[k].append(go_rate)
                    samples[k + "_first"].append(first_rate)
                samples["pointflow"].append(ing.measure(n, count))
                samples["pointflow_hb"].append(ing.hb_rate)
                samples["cpu"].append(ing.cpu_rate)
                if ing_fr is not None:  # frames.fixed set: each chunk placed by the static chain
                    samples.setdefault("frames", []).append(ing_fr.measure(n, count, "lidar"))
                    samples.setdefault("frames_cpu", []).append(ing_fr.cpu_rate)
            med = {k: statistics.median(v) for k, v in samples.items()}
            med.update({k + "_all": [round(x) for x in v] for k, v in samples.items()})
            row = {"chunk_points": n, "chunks": count,
                   "pointflow_pts_s": round(med["pointflow"]), "naive_pts_s": round(med["naive"]),
                   "raw_pts_s": round(med["raw"]),
                   "ingest_pts_per_cpu_s": round(med["cpu"]),
                   "vs_naive": round(med["pointflow"] / med["naive"], 2),
                   # the measure: ingest / raw ZeroMQ, medians of the repeats, every path
                   # timed from the start signal to its last point stored
                   "of_raw": round(med["pointflow"] / med["raw"], 3),
                   # as this bench measured before: pointflow until the heartbeat that shows every
                   # point, raw and naive from their first message received
                   "of_raw_legacy": round(med["pointflow_hb"] / med["raw_first"], 3),
                   "vs_naive_legacy": round(med["pointflow_hb"] / med["naive_first"], 2),
                   "of_raw_each": [round(p / r, 3) for p, r in zip(samples["pointflow"], samples["raw"])],
                   # with frames.fixed set (static chain): ingest / raw, and / the frames-off figure
                   **({"frames_pts_s": round(med["frames"]), "frames_of_raw": round(med["frames"] / med["raw"], 3),
                       "frames_vs_off": round(med["frames"] / med["pointflow"], 3),
                       "frames_of_raw_each": [round(p / r, 3) for p, r in zip(samples["frames"], samples["raw"])]}
                      if "frames" in med else {}),
                   "samples": {k: v for k, v in med.items() if k.endswith("_all")}}
            results["rows"].append(row)
            print(f"{n:>7} pts/chunk  pointflow {med['pointflow'] / 1e6:7.1f} M/s   naive {med['naive'] / 1e6:7.1f} M/s"
                  f"   raw {med['raw'] / 1e6:7.1f} M/s   x{row['vs_naive']:.2f} naive   {row['of_raw'] * 100:.0f}% of raw"
                  f" (legacy timing {row['of_raw_legacy'] * 100:.0f}%)"
                  f"   (ingest process: {med['cpu'] / 1e6:.1f} M pts per CPU-s)"
                  + (f"\n{'':>7} frames.fixed set: {med['frames'] / 1e6:7.1f} M/s   {row['frames_of_raw'] * 100:.0f}% of raw,"
                     f" x{row['frames_vs_off']:.2f} of frames off" if "frames" in med else ""),
                  flush=True)
        targets = {1_000: 0.55, 10_000: 0.65}  # issue 20, frames off; with frames.fixed 0.85 of those
        results["targets"] = {}
        for r in results["rows"]:
            k = r["chunk_points"]
            if k not in targets:
                continue
            t = {"of_raw": r["of_raw"], "target": targets[k], "met": r["of_raw"] >= targets[k],
                 "of_raw_legacy": r["of_raw_legacy"]}
            if "frames_of_raw" in r:
                t.update({"frames_of_raw": r["frames_of_raw"], "frames_target": round(0.85 * targets[k], 4),
                          "frames_met": r["frames_of_raw"] >= 0.85 * targets[k]})
            results["targets"][str(k)] = t
            print(f"target at {k}-point chunks: ingest >= {t['target']:.0%} of raw ZeroMQ: {t['of_raw']:.0%} "
                  f"({'met' if t['met'] else 'missed'}; legacy timing {t['of_raw_legacy']:.0%})"
                  + (f"; frames.fixed set >= {t['frames_target']:.1%}: {t['frames_of_raw']:.0%} "
                     f"({'met' if t['frames_met'] else 'missed'})" if "frames_of_raw" in t else ""), flush=True)
    finally:
        if ing_fr is not None:
            final_fr = ing_fr.close()
            results["frames_final_stats"] = {k: final_fr.get(k) for k in ("points_in", "points_out", "drops", "frames")}
        final = ing.close()
        shutil.rmtree(run_dir, ignore_errors=True)
    results["ingest_final_stats"] = {k: final.get(k) for k in ("points_in", "points_out", "drops", "rejected_messages", "ring_pushes")}
    if os.path.isdir(DATA) and not args.no_replay:
        laz = os.path.join(DATA, "autzen_trim.laz")
        if os.path.exists(laz):
            results["replay"].append(run_replay(os.path.abspath(laz), "autzen_trim.laz", {"chunk_points": 50_000}))
        ouster = os.path.join(DATA, "ouster_os1_128")
        if os.path.isdir(ouster):
            results["replay"].append(run_replay(os.path.abspath(ouster), "ouster_os1_128 (3 scans)",
                                                {"rename": {"reflectivity": "intensity"}, "rate": 1000}))
        for r in results["replay"]:
            print(f"replay {r['what']:<28} {r['points']:>9,} points in {r['seconds_incl_startup']:.2f} s "
                  f"(incl. pipeline start-up), ingest stored {r['points_out']:,}", flush=True)
    H.machine_done(results["machine"])
    H.write_result(args.out, results)


if __name__ == "__main__":
    main()
