"""Whole pipelines under measurement (bench_latency.py, bench_pipeline.py): run a config,
sample its stats after a warm-up and again later."""
from __future__ import annotations

import tempfile

from pointflow import Pipeline


def stats_window(cfg: dict, seconds: float, warmup_s: float, what: str) -> tuple[dict, dict]:
    """Run ``cfg`` and sample stats after a warm-up and again ``seconds`` later; the
    pipeline is stopped either way and a failed run ends the benchmark."""
    pipe = Pipeline.from_dict(cfg, out_dir=tempfile.mkdtemp(prefix="pf-bench-"))
    pipe.start()
    try:
        pipe.wait(warmup_s)
        s0 = pipe.stats()
        pipe.wait(seconds)
        s1 = pipe.stats()
    finally:
        stats = pipe.stop()
    if stats.get("failure"):
        raise SystemExit(f"{what} pipeline failed: {stats['failure']}")
    return s0, s1
