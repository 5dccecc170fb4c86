"""End-to-end latency and tracing overhead, on real pipelines (``pointflow.Pipeline``).

1. Latency: the synthetic lidar at 10 scans/s of 100k points (10 chunks a scan), cadence
   60 Hz, from the source's send of a chunk to the end of the first frame that shows it
   (``send_to_frame`` in the profile; ``end_to_end`` also counts the transport's own time).
   Target (issue 5): p99 <= one tick period + the frame's render time + 5 ms; the bound is
   computed from the same run (frame time = ``frame_done`` span duration).
2. Tracing overhead: the same source unpaced (``realtime: false``) pushing as fast as the
   pipeline takes it, tracing off vs on, alternated; throughput = points through ingest per s.

    XDG_RUNTIME_DIR=/tmp/xdg .venv/bin/python bench/bench_latency.py [--seconds 10] [--backend auto]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pointflow import Pipeline  # noqa: E402
from pointflow.profiling.report import build_profile, format_table  # noqa: E402


def latency_config(backend: str, size: list[int], ring: int) -> dict:
    return {
        "name": "bench-latency",
        "source": {"transport": "synthetic", "options": {"scan_hz": 10, "points_per_scan": 100_000,
                                                         "chunks_per_scan": 10, "cache_scans": 20}},
        "ring": {"max_points": ring},
        "cadence": {"target_hz": 60},
        "render": {"backend": backend, "size": size, "output": {"dir": None}},
        "policy": {"tier": "L"},
        "supervisor": {"max_restarts": 0, "hung_after_ms": 10000},
    }


def throughput_config(tracing: bool) -> dict:
    return {
        "name": "bench-tracing",
        "source": {"transport": "synthetic", "options": {"scan_hz": 10, "points_per_scan": 100_000,
                                                         "chunks_per_scan": 10, "cache_scans": 4,
                                                         "realtime": False}},
        "ring": {"max_points": 500_000},
        "cadence": {"target_hz": 30},
        "render": {"backend": "cpu", "size": [160, 120], "output": {"dir": None}},
        "tracing": {"enabled": tracing},
        "supervisor": {"max_restarts": 0, "hung_after_ms": 10000},
    }


def run_latency(seconds: float, backend: str, size: list[int], ring: int, out_dir: str) -> dict:
    pipe = Pipeline.from_dict(latency_config(backend, size, ring), out_dir=out_dir)
    stats = pipe.run(seconds)
    if stats.get("failure"):
        raise SystemExit(f"latency pipeline failed: {stats['failure']}")
    prof = build_profile(pipe.collector, stats)
    print(format_table(prof))
    s2f = prof.get("send_to_frame") or {}
    frame = prof["stages"].get("frame_done", {}).get("duration", {})
    tick_ms = 1000.0 / 60
    bound_p99 = tick_ms + (frame.get("p99") or 0.0) + 5.0
    render = stats["stages"].get("render", {})
    return {
        "seconds": seconds, "backend": render.get("tier") or render.get("backend") or backend, "size": size,
        "ring_points": ring,
        "send_to_frame_ms": s2f, "end_to_end_ms": prof["end_to_end"],
        "frame_ms": frame, "tick_ms": round(tick_ms, 3),
        "target_p99_ms": round(bound_p99, 3),
        "ratio_p99_to_target": round((s2f.get("p99") or 0) / bound_p99, 3) if s2f.get("p99") else None,
        "cadence": prof.get("cadence"), "frames": stats.get("frames"),
        "stages": {k: {q: v.get(q) for q in ("count", "p50", "p99")} for k, v in prof["stages"].items()},
    }


def run_throughput(seconds: float, tracing: bool) -> float:
    pipe = Pipeline.from_dict(throughput_config(tracing), out_dir=tempfile.mkdtemp(prefix="pf-bench-"))
    stats = pipe.run(seconds)
    if stats.get("failure"):
        raise SystemExit(f"throughput pipeline failed: {stats['failure']}")
    ing = stats["stages"]["ingest"]
    return ing.get("points_in", 0) / max(stats.get("elapsed_s") or seconds, 1e-9)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="latency run length")
    ap.add_argument("--tp-seconds", type=float, default=6.0, help="length of each tracing on/off run")
    ap.add_argument("--tp-rounds", type=int, default=2)
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--ring", type=int, default=1_000_000, help="ring capacity (points kept on screen)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "latency.json"))
    args = ap.parse_args()
    size = [int(v) for v in args.size.split("x")]
    out_dir = tempfile.mkdtemp(prefix="pf-bench-lat-")
    print("== end-to-end latency (100k-point scans at 10 Hz, cadence 60 Hz)")
    lat = run_latency(args.seconds, args.backend, size, args.ring, out_dir)
    print("\n== tracing overhead (unpaced source, ingest throughput)")
    on, off = [], []
    for r in range(args.tp_rounds):
        for tracing in (False, True):
            pts = run_throughput(args.tp_seconds, tracing)
            (on if tracing else off).append(pts)
            print(f"  round {r + 1} tracing {'on ' if tracing else 'off'}: {pts / 1e6:6.2f} M points/s", flush=True)
    med_on, med_off = statistics.median(on), statistics.median(off)
    overhead = 100.0 * (med_off - med_on) / med_off if med_off else 0.0
    s = lat["send_to_frame_ms"]
    print()
    print(f"{'metric':<40}{'value':>14}")
    print("-" * 54)
    print(f"{'send -> frame p50 (ms)':<40}{s.get('p50') or float('nan'):>14.2f}")
    print(f"{'send -> frame p99 (ms)':<40}{s.get('p99') or float('nan'):>14.2f}")
    print(f"{'target p99 = tick + frame p99 + 5 (ms)':<40}{lat['target_p99_ms']:>14.2f}")
    print(f"{'p99 / target':<40}{lat['ratio_p99_to_target'] or float('nan'):>14.3f}")
    print(f"{'frame time p50 / p99 (ms)':<40}{(lat['frame_ms'].get('p50') or 0):>7.2f} / {(lat['frame_ms'].get('p99') or 0):.2f}")
    print(f"{'throughput tracing off (Mpts/s, median)':<40}{med_off / 1e6:>14.2f}")
    print(f"{'throughput tracing on  (Mpts/s, median)':<40}{med_on / 1e6:>14.2f}")
    print(f"{'tracing overhead (%)':<40}{overhead:>14.2f}")
    res = {"benchmark": "latency", "latency": lat,
           "tracing": {"seconds_each": args.tp_seconds, "off_points_per_s": off, "on_points_per_s": on,
                       "median_off": med_off, "median_on": med_on, "ratio_on_off": round(med_on / med_off, 4)
                       if med_off else None, "overhead_pct": round(overhead, 2)},
           "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()}}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(res, indent=1, default=str))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
