"""A/B of the ring's hot path between two checkouts: 10k-point FIFO pushes into a full
100k ring (float64 and float32 positions near [6.4e5, 4.9e6, 0]), and the same float32 chunks
through ingest's ``Ingestor`` (add_chunk + flush), each checkout in its own process,
alternating, medians of all batches. For changes to ``PointRing.push``:

    git archive main pointflow | tar -x -C /tmp/base
    .venv/bin/python bench/ab_ring_push.py /tmp/base . --rounds 10

Prints the medians and the time ratio B/A; nothing is written.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys

import _harness as H


def worker() -> dict[str, list[float]]:
    """Seconds per push, per batch, of the checkout this process imports (``PYTHONPATH``)."""
    import numpy as np

    from pointflow.ring import PointRing

    rng = np.random.default_rng(0)
    cap, n = 100_000, 10_000
    out: dict[str, list[float]] = {}
    for dt in ("f64", "f32"):
        r = PointRing(cap, eviction="drop_oldest", importance_field="importance")
        r.push(rng.uniform(-100, 100, (cap, 3)) + [6.4e5, 4.9e6, 0], importance=rng.random(cap).astype(np.float32))
        pos = rng.uniform(-100, 100, (n, 3)) + [6.4e5, 4.9e6, 0]
        if dt == "f32":
            pos = pos.astype(np.float32)
        imp = rng.random(n).astype(np.float32)

        out[dt] = H.per_call(lambda: r.push(pos, importance=imp))
        r.close()
    # the same through ingest's Ingestor (convert, non-finite check, queue, push), float32 chunks
    from pointflow.chunk import PointChunk
    from pointflow.ingest.process import Ingestor

    r = PointRing(cap, eviction="drop_oldest", importance_field="importance")
    r.push(rng.uniform(-100, 100, (cap, 3)) + [6.4e5, 4.9e6, 0], importance=rng.random(cap).astype(np.float32))
    ing = Ingestor(r, coalesce_points=n)
    pos32 = (rng.uniform(-100, 100, (n, 3)) + [6.4e5, 4.9e6, 0]).astype(np.float32)

    def g():
        ing.add_chunk(PointChunk(positions=pos32, channels={}))
        ing.flush()

    out["ingest_f32"] = H.per_call(g)
    r.close()
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a", help="checkout A (the baseline)")
    ap.add_argument("b", help="checkout B")
    ap.add_argument("--rounds", type=int, default=8)
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(worker()))
        return 0
    roots = {"A": args.a, "B": args.b}
    res: dict[str, dict[str, list[float]]] = {k: {"f64": [], "f32": [], "ingest_f32": []} for k in roots}
    runs = H.interleave({k: (lambda root=root: H.run_json([__file__, root, root, "--worker"], root))
                         for k, root in roots.items()}, args.rounds)
    for k, outs in runs.items():
        for o in outs:
            for d in o:
                res[k][d] += o[d]
    for d in ("f64", "f32", "ingest_f32"):
        m = {k: statistics.median(res[k][d]) * 1e6 for k in roots}
        print(f"{d}: A {m['A']:.1f} us ({1e4 / m['A']:.0f} Mpts/s)  B {m['B']:.1f} us ({1e4 / m['B']:.0f} Mpts/s)  "
              f"B/A time {m['B'] / m['A']:.3f}  ({len(res['A'][d])} batches each)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
