"""GPU timestamp queries reach the stats and the profiler's trace (wgpu tier)."""
from __future__ import annotations

import json

import pytest

from pointflow import Pipeline
from pointflow.profiling.report import write_profile

from ..helpers import small_config


def test_gpu_timings_in_stats_and_trace(tmp_path):
    from gpu_util import require_adapter

    require_adapter()
    cfg = small_config(render={"backend": "wgpu", "size": [160, 120], "output": {"every_n_frames": 1000}})
    pipe = Pipeline.from_dict(cfg, out_dir=str(tmp_path))
    with pipe:
        pipe.wait(60, until=lambda: pipe.stats()["frames"] >= 8)
    stats = pipe.stats()
    render = stats["stages"]["render"]
    assert render["tier"] == "wgpu"
    if not render["tier_info"].get("timestamps"):  # lavapipe (CI) has them; some drivers do not
        pytest.skip(f"adapter {render['tier_info'].get('adapter')} has no timestamp queries")
    assert render["tier_gpu_draw_ms"] > 0
    write_profile(str(tmp_path), pipe.collector, stats)
    trace = json.loads((tmp_path / "trace.json").read_text())
    gpu = [e for e in trace["traceEvents"] if e.get("ph") == "X" and e["name"] in ("gpu_compute", "gpu_draw")]
    assert gpu, "no GPU slices in trace.json"
    assert {e["pid"] for e in gpu} == {render["pid"]}, "GPU slices belong on the render track"
    prof = json.loads((tmp_path / "profile.json").read_text())
    assert prof["stages"]["gpu_draw"]["count"] >= 1
