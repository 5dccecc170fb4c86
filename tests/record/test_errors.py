"""A disk that fills up and a path that cannot be written: one clear line, no traceback;
when the disk fills, the pipeline runs on without the recording and counts what it missed."""
from __future__ import annotations

import subprocess

import pytest
import yaml

from pointflow import cli
from pointflow.record.inspect import record_summary
from pointflow.runtime.pipeline import Pipeline

from .helpers import read_recording, require_root


def _yaml(tmp_path, **over) -> str:
    cfg = {"source": {"transport": "synthetic", "options": {"scan_hz": 10, "points_per_scan": 50000}},
           "ring": {"max_points": 200_000},
           "render": {"backend": "cpu", "size": [64, 48], "output": {"every_n_frames": 1000}},
           # a stage starved for a while on a loaded machine is not hung (kills are found by exit code)
           "supervisor": {"max_restarts": 0, "hung_after_ms": 10_000}, **over}
    p = tmp_path / "p.yaml"
    p.write_text(yaml.safe_dump(cfg))
    return str(p)


@pytest.fixture
def small_disk(tmp_path):
    require_root("mounting a 2 MB tmpfs")
    d = tmp_path / "small"
    d.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(d)], check=True, timeout=30)
    try:
        yield d
    finally:
        subprocess.run(["umount", "-l", str(d)], check=False, timeout=30)


def test_disk_full_stops_only_the_recording(tmp_path, small_disk, capfd):
    rec = small_disk / "rec.mcap"
    cfg = yaml.safe_load(open(_yaml(tmp_path, record={"path": str(rec)})))
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path / "out")) as pipe:
        recorder = lambda: pipe.stats()["stages"]["recorder"]
        written = lambda: pipe.stats()["stages"]["ingest"]["points_out"]
        pipe.wait(120, until=lambda: recorder().get("record_error") == "disk_full")
        assert recorder().get("record_error") == "disk_full"
        n = written()
        pipe.wait(60, until=lambda: written() > n + 200_000)
        assert written() > n + 200_000, "ingest runs on after the disk filled"
        st = pipe.stop()
    err = capfd.readouterr().err  # the stage processes' stderr
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if "recording stopped" in ln]
    assert len(lines) == 1 and "No space left on device" in lines[0] and str(rec) in lines[0], err[-3000:]
    r, ing, acc = st["stages"]["recorder"], st["stages"]["ingest"], st["accounting"]
    assert r["restarts"] == 0 and r["alive"] is False and r["record_error"] == "disk_full"
    assert r["drops"]["disk_full"] > 0
    assert ing["points_out"] > r["points_out"] > 0
    assert acc["recorder_balanced"] and acc["record_tap_balanced"] and acc["ingest_balanced"]
    assert "recording stopped: disk_full" in record_summary(st)
    msgs = read_recording(str(rec), tolerant=True)  # what fitted is readable
    assert msgs and [m.sequence for m in msgs] == list(range(len(msgs)))


@pytest.mark.parametrize("where", ["under_a_file", "a_directory", "read_only"])
def test_unwritable_path_is_one_line(tmp_path, capsys, where):
    if where == "under_a_file":
        (tmp_path / "f").write_text("x")
        path = str(tmp_path / "f" / "rec.mcap")
    elif where == "a_directory":
        path = str(tmp_path)
    else:
        require_root("a read-only bind mount")
        d = tmp_path / "ro"
        d.mkdir()
        subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m,ro", "tmpfs", str(d)], check=True, timeout=30)
        path = str(d / "rec.mcap")
    try:
        code = cli.main(["run", _yaml(tmp_path), "--duration", "1", "-q", "--out", str(tmp_path / "out"),
                         "--record", path])
    finally:
        if where == "read_only":
            subprocess.run(["umount", "-l", str(tmp_path / "ro")], check=False, timeout=30)
    err = capsys.readouterr().err
    assert code == cli.EXIT_CONFIG
    lines = [ln for ln in err.splitlines() if ln.startswith("config error")]
    assert len(lines) == 1 and "record.path" in lines[0], err
    assert "Traceback" not in err
