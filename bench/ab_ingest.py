"""A/B of the ingest stage between two checkouts with bench_ingest.py's measurement: each
round runs this checkout's ``bench_ingest.py`` once against each checkout's ``pointflow``
(separate processes, alternating order), so both are timed the same way next to a raw
ZeroMQ run of their own; prints the ingest / raw ratios per round and their medians.

    git archive <base> pointflow | tar -x -C /tmp/base
    .venv/bin/python bench/ab_ingest.py /tmp/base . --rounds 4 -- --points 10000000 --repeats 3 --sizes 1000,10000

With ``--loop`` it measures instead, in one process per checkout (alternating), the CPU time
per chunk of the ingest stage's own loop body on pre-sent messages (1k and 10k-point chunks
from ``wire.encode``, received from a real ZeroMQ socket, decoded, checked, queued and pushed
into a 2M-point ring): the stage's cost without the sender and the machine's other load
(min over batches of process time, so a busy shared machine disturbs it least).

    .venv/bin/python bench/ab_ingest.py /tmp/base . --loop --rounds 6

Nothing is written but temporary files.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile

import _harness as H

BENCH = str(H.BENCH / "bench_ingest.py")


def loop_worker() -> dict[str, float]:
    """us of process time per chunk for the ingest loop body of the checkout this process
    imports (``PYTHONPATH``, set by the driver)."""
    import time

    import numpy as np
    import zmq

    from pointflow import wire
    from pointflow.chunk import PointChunk
    from pointflow.config import load_config
    from pointflow.ingest import process
    from pointflow.ring import PointRing

    cfg = load_config({"source": {"transport": "synthetic"}, "ring": {"max_points": 2_000_000},
                       "render": {"color_by": "intensity", "output": {"dir": None}}})
    ring = PointRing(2_000_000, channels=cfg.ring_channels())
    zc = zmq.Context()
    pull, push = zc.socket(zmq.PULL), zc.socket(zmq.PUSH)
    pull.set_hwm(0)
    push.set_hwm(0)
    pull.bind("inproc://ab-ingest")
    push.connect("inproc://ab-ingest")
    out = {}
    for n in (1_000, 10_000):
        ing = process.Ingestor(ring, importance_field=cfg.ring.importance_field)
        rng = np.random.default_rng(n)
        pos, inten = rng.uniform(-100, 100, (n, 3)).astype(np.float32), rng.uniform(0, 255, n).astype(np.float32)
        k = 200_000 // n  # chunks per batch
        best = float("inf")
        copy = True
        for b in range(12):
            for i in range(k):
                wire.send(push, PointChunk(positions=pos, channels={"intensity": inten}, source_id="bench", seq=i, trace_id=0))
            time.sleep(0.02)
            t0 = time.process_time()
            for _ in range(k):  # the stage's loop body (burst drained, then flush), as each checkout has it
                if hasattr(process, "recv_frames"):
                    frames = process.recv_frames(pull)
                else:
                    frames = pull.recv_multipart(zmq.NOBLOCK, copy=copy)
                    big = frames[-1] if len(frames) < 2 else frames[1]
                    copy = (len(big) if copy else big.buffer.nbytes) < wire.ZERO_COPY_MIN_BYTES
                ing.receive(frames)
                if len(ing.queue) >= 8:
                    ing.flush()
            ing.flush()
            dt = time.process_time() - t0
            if b >= 2:  # warm-up batches touch the ring's pages first
                best = min(best, dt / k * 1e6)
        assert ing.counters.points_out == 12 * k * n, ing.stats_extra()
        out[f"{n}"] = best
    ring.close()
    return out


def loop_main(roots: dict[str, str], rounds: int) -> int:
    runs = H.interleave({k: (lambda root=root: H.run_json([__file__, root, root, "--loop-worker"], root))
                         for k, root in roots.items()}, rounds)
    res: dict[str, dict[str, list[float]]] = {k: {} for k in roots}
    for k, outs in runs.items():
        for o in outs:
            for n, v in o.items():
                res[k].setdefault(n, []).append(v)
    for n in res["A"]:
        m = {k: statistics.median(res[k][n]) for k in roots}
        print(f"{n:>6}-point chunks: A {m['A']:.1f} us/chunk  B {m['B']:.1f} us/chunk (process time, median of "
              f"{rounds} rounds of min over batches)  B/A {m['B'] / m['A']:.2f}   "
              f"A {[round(x, 1) for x in res['A'][n]]}  B {[round(x, 1) for x in res['B'][n]]}")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a", help="checkout A (the baseline): a folder holding pointflow/")
    ap.add_argument("b", help="checkout B")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--loop", action="store_true", help="CPU time per chunk of the stage's loop body, in-process")
    ap.add_argument("--loop-worker", action="store_true", help=argparse.SUPPRESS)
    args, bench_args = ap.parse_known_args()  # the rest (after --) goes to bench_ingest.py
    bench_args = [a for a in bench_args if a != "--"]
    if args.loop_worker:
        print(json.dumps(loop_worker()))
        return 0
    roots = {"A": os.path.abspath(args.a), "B": os.path.abspath(args.b)}
    if args.loop:
        return loop_main(roots, args.rounds)
    with tempfile.TemporaryDirectory() as tmp:
        def one(k: str, root: str) -> dict:
            out = os.path.join(tmp, "out.json")
            # cwd and PYTHONPATH put this checkout's pointflow first (before the editable install)
            subprocess.run([sys.executable, BENCH, "--no-replay", "--out", out, *bench_args], cwd=root,
                           env=H.checkout_env(root), check=True, stdout=subprocess.DEVNULL)
            with open(out) as f:
                return json.load(f)

        def show(i: int, k: str, res: dict) -> None:
            line = "  ".join(f"{r['chunk_points']}: {r['of_raw']:.0%} (legacy {r['of_raw_legacy']:.0%})" for r in res["rows"])
            print(f"round {i} {k}: of raw {line}   load {res['machine']['loadavg_before'][0]:.1f}", flush=True)

        rows = H.interleave({k: (lambda k=k, root=root: one(k, root)) for k, root in roots.items()}, args.rounds, show)
    sizes = [r["chunk_points"] for r in rows["A"][0]["rows"]]
    for n in sizes:
        for key in ("of_raw", "of_raw_legacy", "ingest_pts_per_cpu_s"):
            vals = {k: [next(r[key] for r in res["rows"] if r["chunk_points"] == n) for res in rows[k]] for k in roots}
            m = {k: statistics.median(v) for k, v in vals.items()}
            print(f"{n:>6} {key:<22} A median {m['A']:.3g} ({min(vals['A']):.3g}..{max(vals['A']):.3g})   "
                  f"B median {m['B']:.3g} ({min(vals['B']):.3g}..{max(vals['B']):.3g})   B/A {m['B'] / m['A']:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
