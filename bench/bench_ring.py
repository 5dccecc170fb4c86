"""Ring throughput benchmark.

Points/s for FIFO and importance ingest into a *full* ring (capacities 100k and 1M, chunks of
1k/10k/100k points), and the time of a full 1M-point snapshot into a slab, each next to a plain
``numpy.copyto`` of the same number of bytes measured in the same run (the memory-bandwidth limit).

    XDG_RUNTIME_DIR=/tmp/xdg .venv/bin/python bench/bench_ring.py [--quick] [--out bench/results/ring.json]

What the ingest baseline copies: per point, exactly the bytes the ring writes per point
(``bytes_per_point``: 28 B for these rings = positions f32 x3, t_ingest_ms f64, importance f32,
generation u32; 32 B before ring version 2, whose generation was u64), from a cache-resident
source of that size into a ring-sized destination at rotating offsets (so the destination is as
cache-cold as the ring's arrays). It reads and writes that many bytes per point; the ring reads
28 B of input per point (positions f64 x3, importance f32), plus its cached origin tile, and
writes the same bytes, split over four arrays.

Ingest: FIFO, importance and copy are timed in interleaved batches (each repeat runs one batch
of each), so a burst of load from other processes hits all three alike; the figures are the
medians over ``--repeats`` batches (``*_best`` fields: the fastest batch of each). The ratios
are ratios of the medians. The snapshot figures are the best of ``--repeats``.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np

import _harness as H
from pointflow.ring import PointRing, SlabPair, SlabWriter


def best_time(fn, min_batch_s: float, repeats: int) -> float:
    """Best per-call time over `repeats` batches of at least `min_batch_s` each."""
    return min(H.per_call(fn, repeats, min_batch_s, warm=1))



def interleaved_times(fns: dict, min_batch_s: float, repeats: int) -> dict[str, list[float]]:
    """Per-call times of each function, one batch of each per repeat, in turn."""
    for fn in fns.values():
        fn()  # warm up
    out = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            out[k].append(H.batch_time(fn, min_batch_s))
    return out


def bytes_per_point(ring: PointRing) -> int:
    return sum(a.itemsize * (a.size // ring.capacity) for a in ring.arrays.values())


def bench_ingest(cap: int, chunks, repeats: int, batch_s: float, rng) -> list[dict]:
    rows = []
    rings = {
        "fifo": PointRing(cap, eviction="drop_oldest", importance_field="importance"),
        "importance": PointRing(cap, eviction="importance", importance_field="importance", max_staleness_ms=1000.0),
    }
    try:
        for r in rings.values():
            r.push(rng.uniform(-100, 100, (cap, 3)) + [6.4e5, 4.9e6, 0], importance=rng.random(cap).astype(np.float32))
        bpp = bytes_per_point(rings["fifo"])
        for n in chunks:
            pos = rng.uniform(-100, 100, (n, 3)) + [6.4e5, 4.9e6, 0]
            imp = rng.random(n).astype(np.float32)
            # the same bytes with a plain copy, into a ring-sized destination at rotating offsets
            src = np.ones(n * bpp // 4, np.float32)
            dst = np.zeros(cap * bpp // 4, np.float32)
            state = {"off": 0}
            step = src.shape[0]

            def copy():
                o = state["off"]
                if o + step > dst.shape[0]:
                    o = 0
                np.copyto(dst[o:o + step], src)
                state["off"] = o + step

            fns = {mode: (lambda r=r: r.push(pos, importance=imp)) for mode, r in rings.items()}
            fns["copy"] = copy
            times = interleaved_times(fns, batch_s, repeats)
            for r in rings.values():
                assert r.stats().total_points == cap
            t = {k: statistics.median(v) for k, v in times.items()}
            best = {k: min(v) for k, v in times.items()}
            t_copy = t["copy"]
            rows.append({
                "capacity": cap, "chunk": n, "bytes_per_point": bpp,
                "fifo_pts_per_s": n / t["fifo"], "importance_pts_per_s": n / t["importance"],
                "copy_pts_per_s": n / t_copy,
                "fifo_us": t["fifo"] * 1e6, "importance_us": t["importance"] * 1e6, "copy_us": t_copy * 1e6,
                "fifo_vs_copy": t_copy / t["fifo"], "importance_vs_fifo_cost": t["importance"] / t["fifo"],
                "fifo_us_best": best["fifo"] * 1e6, "importance_us_best": best["importance"] * 1e6,
                "copy_us_best": best["copy"] * 1e6, "fifo_vs_copy_best": best["copy"] / best["fifo"],
                "fifo_vs_copy_spread": [round(min(times["copy"]) / max(times["fifo"]), 3),
                                        round(max(times["copy"]) / min(times["fifo"]), 3)],
            })
    finally:
        for r in rings.values():
            r.close()
    return rows


def bench_snapshot(cap: int, repeats: int, rng) -> dict:
    import zmq

    ctx = zmq.Context()
    pull = ctx.socket(zmq.PULL)
    pull.bind("inproc://bench-ready")
    push = ctx.socket(zmq.PUSH)
    push.connect("inproc://bench-ready")
    rel = ctx.socket(zmq.PULL)
    rel.bind("inproc://bench-rel")
    with PointRing(cap, channels=(), importance_field="importance") as ring, SlabPair.create(ring.layout) as slabs:
        ring.push(rng.uniform(-100, 100, (cap, 3)), importance=rng.random(cap).astype(np.float32))
        writer = SlabWriter(ring, slabs, push, rel)
        nbytes = sum(a.nbytes for a in ring.arrays.values())

        def full_copy():
            with ring.lock():
                writer.copy_to_slab(0, None)

        t_snap = best_time(full_copy, 0.0, repeats)
        src = np.ones(nbytes // 4, np.float32)
        dst = np.zeros(nbytes // 4, np.float32)
        t_copy = best_time(lambda: np.copyto(dst, src), 0.0, repeats)

        # whole publish (lock, full copy, channel ranges, ZeroMQ send), then an incremental one
        def full_publish():
            writer.reset_reader()
            writer._pending = [None, None]
            h = writer.publish()
            pull.recv_multipart()
            return h

        t_pub_full = best_time(full_publish, 0.0, repeats)
        chunk = rng.uniform(-100, 100, (10_000, 3))

        def incr_publish():
            writer.reset_reader()
            writer._force_full = False
            ring.push(chunk)
            writer.publish()
            pull.recv_multipart()

        t_pub_incr = best_time(incr_publish, 0.05, repeats)
        t_push = best_time(lambda: ring.push(chunk), 0.05, repeats)
    for s in (pull, push, rel):
        s.close(0)
    ctx.term()
    return {"capacity": cap, "bytes": nbytes, "snapshot_ms": t_snap * 1e3, "copy_ms": t_copy * 1e3,
            "snapshot_vs_copy_time": t_snap / t_copy, "publish_full_ms": t_pub_full * 1e3,
            "publish_after_10k_push_ms": max(0.0, (t_pub_incr - t_push)) * 1e3}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer/shorter repeats")
    ap.add_argument("--repeats", type=int, default=None)
    ap.add_argument("--out", default=str(H.RESULTS / "ring.json"))
    args = ap.parse_args(argv)
    repeats = args.repeats or (5 if args.quick else 9)
    batch_s = 0.03 if args.quick else 0.08
    rng = np.random.default_rng(0)
    machine = H.machine(numpy=np.__version__)
    load0 = machine["loadavg_before"]
    rows = []
    for cap in (100_000, 1_000_000):
        rows += bench_ingest(cap, (1_000, 10_000, 100_000), repeats, batch_s, rng)
    snap = bench_snapshot(1_000_000, repeats, rng)

    print(f"medians of {repeats} interleaved batches; load average at start {load0[0]:.2f}")
    print(f"{'capacity':>9} {'chunk':>7} {'FIFO Mpt/s':>11} {'imp Mpt/s':>10} {'copy Mpt/s':>11} "
          f"{'FIFO/copy':>10} {'(best/best)':>11} {'imp cost/FIFO':>14}")
    for r in rows:
        print(f"{r['capacity']:>9} {r['chunk']:>7} {r['fifo_pts_per_s'] / 1e6:>11.1f} "
              f"{r['importance_pts_per_s'] / 1e6:>10.1f} {r['copy_pts_per_s'] / 1e6:>11.1f} "
              f"{r['fifo_vs_copy']:>10.2f} {r['fifo_vs_copy_best']:>11.2f} {r['importance_vs_fifo_cost']:>14.2f}")
    print(f"snapshot of {snap['capacity']} points ({snap['bytes'] / 1e6:.0f} MB): {snap['snapshot_ms']:.2f} ms, "
          f"copyto {snap['copy_ms']:.2f} ms, ratio {snap['snapshot_vs_copy_time']:.2f}; full publish "
          f"{snap['publish_full_ms']:.2f} ms; publish after a 10k push {snap['publish_after_10k_push_ms']:.3f} ms")
    fifo10k = [r for r in rows if r["chunk"] == 10_000]
    targets = {
        "fifo_10k_vs_copy_min": min(r["fifo_vs_copy"] for r in fifo10k), "fifo_10k_vs_copy_target": 0.5,
        "importance_vs_fifo_cost_max": max(r["importance_vs_fifo_cost"] for r in rows),
        "importance_vs_fifo_cost_target": 3.0,
        "snapshot_vs_copy_time": snap["snapshot_vs_copy_time"], "snapshot_vs_copy_target": 2.0,
    }
    print("targets:", json.dumps({k: round(v, 3) for k, v in targets.items()}))
    out = {
        "benchmark": "ring", "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "machine": H.machine_done(machine), "command": H.command(),
        "repeats": repeats, "statistic": "ingest: medians of interleaved batches; snapshot: best of repeats",
        "loadavg_at_start": load0, "ingest": rows, "snapshot": snap, "targets": targets,
    }
    H.write_result(args.out, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
