"""Measured crossovers come from one place (pointflow.render.calibration): the user cache,
then the defaults shipped in the package; never the checkout's bench/results/."""
from __future__ import annotations

import json
import re
from pathlib import Path

from pointflow.render import calibration, select
from pointflow.render.wgpu_tier import raster

PKG = Path(__file__).resolve().parents[2] / "pointflow"


def test_shipped_defaults_then_user_cache(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.delenv("POINTFLOW_CROSSOVER", raising=False)
    px, ppp, where = raster.crossover()
    assert where == "shipped default raster_crossover.json" and px > 0 and ppp > 0
    assert select.crossover_points()[1] == "shipped default crossover.json"
    p = calibration.install("raster_crossover.json", {"max_compute_point_px": 3.0,
                                                      "min_compute_points_per_pixel": 0.5, "extra": 1})
    assert p == tmp_path / "pointflow" / "raster_crossover.json"
    assert raster.crossover() == (3.0, 0.5, str(p))
    # a broken or incomplete cache file falls back to the shipped default, not an error
    p.write_text("{not json")
    assert raster.crossover()[2] == "shipped default raster_crossover.json"
    p.write_text(json.dumps({"max_compute_point_px": 3.0}))
    assert raster.crossover()[2] == "shipped default raster_crossover.json"


def test_library_code_never_reads_bench_results():
    hits = [str(f.relative_to(PKG)) for f in PKG.rglob("*.py")
            if re.search(r"""["']bench["']\s*/\s*["']results["']|["'][^"'`\n]*bench/results""", f.read_text())]
    assert not hits, f"library modules naming bench/results: {hits}"
