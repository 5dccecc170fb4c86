"""Soak: memory stays bounded while a source outruns the ring for a long time.

A synthetic source replays cached scans as fast as it can (many times the ring's capacity
per second) into a small ring, rendered by the cpu tier. Every second the supervisor's
stats are sampled: per-stage RSS, ring fill, ingest counts. The baseline is each stage's
median RSS over the first third after the warm-up (same run); the result is the median over
the last third divided by it (1.0 = no growth) and the peak, plus the accounting check. Prints a table and writes bench/results/soak.json.

    .venv/bin/python bench/bench_soak.py --seconds 60
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from pointflow import Pipeline

RESULTS = Path(__file__).resolve().parent / "results"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--warmup", type=float, default=10.0)
    ap.add_argument("--ring", type=int, default=200_000)
    args = ap.parse_args()
    os.environ.setdefault("XDG_RUNTIME_DIR", "/tmp")
    cfg = {
        "source": {"transport": "synthetic",
                   "options": {"points_per_scan": 100_000, "realtime": False, "cache_scans": 4}},
        "ring": {"max_points": args.ring},
        "cadence": {"target_hz": 30},
        "render": {"backend": "cpu", "size": [320, 240], "output": {"dir": None}},
    }
    samples = []
    pipe = Pipeline.from_dict(cfg, out_dir=None)
    with pipe:
        t0 = time.monotonic()
        next_t = t0
        while time.monotonic() - t0 < args.seconds:
            pipe.wait(max(0.0, next_t - time.monotonic()))
            next_t += 1.0
            st = pipe.stats()
            samples.append({
                "t": round(time.monotonic() - t0, 2),
                "rss_mb": {n: round(s.get("rss_bytes", 0) / 2**20, 1) for n, s in st["stages"].items()},
                "ring_points": (st.get("ring") or {}).get("total_points"),
                "ingest_in": st["stages"]["ingest"]["points_in"],
                "frames": st["frames"],
            })
    final = pipe.stats()
    warm = [s for s in samples if s["t"] >= args.warmup] or samples
    first, last = warm[0], warm[-1]
    # RSS breathes with the allocator (chunks in flight); a leak shows as the late median
    # rising above the early one, so compare medians of the first and last thirds
    third = max(1, len(warm) // 3)
    med = lambda rows, n: float(np.median([r["rss_mb"][n] for r in rows]))
    early = {n: med(warm[:third], n) for n in last["rss_mb"]}
    late = {n: med(warm[-third:], n) for n in last["rss_mb"]}
    growth = {n: round(late[n] / early[n], 3) if early[n] else None for n in last["rss_mb"]}
    peak = {n: max(s["rss_mb"][n] for s in warm) for n in last["rss_mb"]}
    secs = last["t"] - first["t"]
    rate = (last["ingest_in"] - first["ingest_in"]) / secs if secs > 0 else 0.0
    out = {
        "benchmark": "soak", "seconds": args.seconds, "warmup_s": args.warmup, "ring_points": args.ring,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
        "ingest_points_per_s": round(rate), "ring_turnovers": round((last["ingest_in"] - first["ingest_in"]) / args.ring, 1),
        "rss_mb_early_median": early, "rss_mb_late_median": late, "rss_mb_peak": peak,
        "rss_growth_ratio_late_vs_early": growth, "accounting": final.get("accounting"), "frames": final.get("frames"),
        "samples": samples,
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "soak.json").write_text(json.dumps(out, indent=2))
    print(f"soak: {secs:.0f} s after a {args.warmup:.0f} s warm-up, {rate / 1e6:.1f} M points/s into a "
          f"{args.ring:,}-point ring ({out['ring_turnovers']} turnovers), {out['frames']} frames")
    print(f"{'stage':10s} {'early median MB':>16s} {'late median MB':>15s} {'peak MB':>8s} {'late/early':>10s}")
    for n in last["rss_mb"]:
        print(f"{n:10s} {early[n]:16.1f} {late[n]:15.1f} {peak[n]:8.1f} {growth[n]!s:>10s}")
    acc = final.get("accounting") or {}
    print(f"accounting: ingest balanced {acc.get('ingest_balanced')}, ring agrees {acc.get('ring_agrees')}, "
          f"lost before ingest {acc.get('lost_before_ingest')}")
    print(f"wrote {RESULTS / 'soak.json'}")


if __name__ == "__main__":
    main()
