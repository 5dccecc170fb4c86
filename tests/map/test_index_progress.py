"""The index build's progress as the map stage shows it (issue 37): a log line per tenth whose
percentage is the points counted (not "697720 of 697721 points (90%)"), ``map_index_pct`` for
the run's live line, and that line: ``map: indexing 35%`` while nothing is drawn, then the points."""
from __future__ import annotations

import logging
import types

from pointflow.map.process import index_progress
from pointflow.profiling.report import live_summary

from .mapfiles import write_las


def test_index_progress_lines_say_the_share_of_points(tmp_path, caplog):
    from pointflow.map import open_map

    counters = types.SimpleNamespace(extra={})
    seen = []
    log = logging.getLogger("test.map")
    progress = index_progress(log, counters)

    def both(done, total):
        progress(done, total)
        seen.append((done, total, counters.extra["map_index_pct"]))

    path = write_las(str(tmp_path / "tile.laz"), 30_000)
    with caplog.at_level(logging.INFO, logger="test.map"):
        open_map(path, cache_dir=str(tmp_path / "cache"), progress=both).close()
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("map index: ")]
    assert lines[-1] == "map index: 100% (30000 of 30000 points)"
    for done, total, pct in seen:
        assert pct == min(100, 100 * done // total)
    assert all(p < 100 for d, t, p in seen[:-1]) and seen[-1][2] == 100, "100 % once, at the end"
    for ln in lines:  # each line's percentage is its own count's
        pct, rest = ln[len("map index: "):].split("% (")
        done, total = (int(v) for v in rest.split(" points")[0].split(" of "))
        assert int(pct) == 100 * done // total


def test_live_line_says_indexing_then_the_points_drawn():
    stats = {"stages": {"map": {"kind": "map", "map_index_pct": 35, "map_ready": False},
                        "render": {"kind": "render", "map_points": 0}}}
    assert "map: indexing 35%" in live_summary(stats)
    stats["stages"]["render"]["map_points"] = 43_691  # a preview drawn while the index is built
    assert "map: indexing 35% map=43.7k" in live_summary(stats)
    stats["stages"]["map"].update(map_index_pct=None, map_ready=True)
    stats["stages"]["render"]["map_points"] = 697_721
    line = live_summary(stats)
    assert "map=697.7k" in line and "indexing" not in line
    stats["stages"]["map"]["map_error"] = "tile.laz: not a valid LAS/LAZ file"
    assert "map=error" in live_summary(stats)


def test_index_progress_lines_say_the_time_left(caplog, monkeypatch):
    """Past half a second, a tenth's line says about how long is left from the rate so far
    (the pipeline's lines had no ETA, the command line's progress line had one)."""
    import pointflow.map.process as mp

    now = [100.0]
    monkeypatch.setattr(mp.time, "monotonic", lambda: now[0])
    progress = index_progress(logging.getLogger("test.eta"))
    with caplog.at_level(logging.INFO, logger="test.eta"):
        progress(0, 1000)
        now[0] += 10.0
        progress(250, 1000)   # 250 points in 10 s: 750 left, 30 s
        now[0] += 20.0
        progress(1000, 1000)
    lines = [r.getMessage() for r in caplog.records]
    assert lines == ["map index: 0% (0 of 1000 points)", "map index: 25% (250 of 1000 points, about 30 s left)",
                     "map index: 100% (1000 of 1000 points)"], lines
