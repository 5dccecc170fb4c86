"""What `pointflow run` says from its first instant (issue 36, item 4): what it starts, each
stage as it reports in, that it runs; a `--duration` that is no duration refused; a run
that drew no frame says so and why instead of pointing at an empty folder."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import pytest
import yaml

from pointflow.cli import EXIT_CONFIG, main, no_frame_reason

from ..helpers import small_config


def _run(tmp_path, cfg: dict, *args: str) -> subprocess.CompletedProcess:
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump(cfg))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    return subprocess.run([sys.executable, "-m", "pointflow.cli", "run", str(p), "--out", str(tmp_path / "out"), *args],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=240)


def test_run_says_what_it_starts_before_any_stage_is_ready(tmp_path):
    r = _run(tmp_path, small_config(), "--duration", "1")
    assert r.returncode == 0, r.stderr[-3000:]
    err = r.stderr
    assert err.startswith("starting "), err[-3000:]  # the first thing said, before anything is up
    assert "render, cadence, ingest, source" in err.splitlines()[0]
    # found by position in the text, not line by line: the stages' own log lines share stderr, and a
    # line of this process can land inside one of theirs (seen once in a CI run)
    ready = {m.group(1): m.start() for m in re.finditer(r"ready: (\w+) \(", err)}
    assert sorted(ready) == ["cadence", "ingest", "render", "source"], err[-3000:]
    running = err.index("running after ")
    assert max(ready.values()) < running and "stopping in 1 s" in err[running:].splitlines()[0]
    progress = [m.start() for m in re.finditer(r"(?m)^t=", err)]
    assert progress and min(progress) > running
    assert "frames and stats.json in" in r.stdout


@pytest.mark.parametrize("value", ["-1", "0", "nan", "inf"])
def test_a_duration_that_is_no_duration_is_refused(tmp_path, capsys, monkeypatch, value):
    monkeypatch.chdir(tmp_path)
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump(small_config()))
    assert main(["run", str(p), f"--duration={value}", "-q"]) == EXIT_CONFIG
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--duration: must be a number of seconds greater than 0" in err, err
    assert "Traceback" not in err and not (tmp_path / "out").exists()  # nothing started


def test_a_run_that_drew_no_frame_says_so_and_why(tmp_path):
    """An api source nobody feeds: the stages run, no point reaches the ring, nothing is drawn."""
    cfg = small_config(source={"transport": "api"})
    r = _run(tmp_path, cfg, "--duration", "0.5", "-q")
    assert r.returncode == 0, r.stderr[-3000:]
    assert "no frame drawn: no point reached the ring (the sources sent 0)" in r.stdout, r.stdout
    assert "frames and stats.json" not in r.stdout and f"stats.json in {tmp_path / 'out'}" in r.stdout
    assert json.loads((tmp_path / "out" / "stats.json").read_text())["frames"] == 0


def test_the_reason_names_the_stage_that_was_not_ready_or_compiling():
    starting = {"stages": {"render": {"ready": False, "startup_ms": {"interpreter": 900.0}}}}
    assert "render stage was still starting" in no_frame_reason(starting)
    compiling = {"stages": {"render": {"ready": True, "startup_ms": {"ready": 800.0}, "raster": "compiling"}}}
    assert "still compiling its raster" in no_frame_reason(compiling)
    compiled = {"stages": {"render": {"ready": True, "startup_ms": {"ready": 800.0}, "raster": "compiled"},
                           "src": {"kind": "source", "points_out": 0}}}
    assert no_frame_reason(compiled) == "no frame drawn: no point reached the ring (the sources sent 0)"
    assert no_frame_reason({"stages": {"render": {"frames": 2, "pngs": 0}}}) is None  # saved as last.png
    assert no_frame_reason({"stages": {"sender": {}}}) is None  # no render stage: nothing to say


def test_an_unknown_flag_is_refused_by_its_command_with_the_closest_flag(capsys):
    """A typo after ``run`` gets ``run``'s usage and the flag meant; one before any command
    gets the top level's; nothing starts (argparse's exit 2)."""
    for argv, usage, says in ((["run", "x.yaml", "--duraton", "5"], "usage: pointflow run ",
                               "pointflow run: error: unrecognized arguments: --duraton 5 (did you mean --duration?)"),
                              (["validate", "x.yaml", "--bogus"], "usage: pointflow validate ",
                               "pointflow validate: error: unrecognized arguments: --bogus\n"),
                              (["--bogus", "run", "x.yaml"], "usage: pointflow [-h]",
                               "pointflow: error: unrecognized arguments: --bogus\n")):
        with pytest.raises(SystemExit) as e:
            main(argv)
        err = capsys.readouterr().err
        assert e.value.code == 2 and err.startswith(usage) and says in err, err


def test_python_dash_m_pointflow_is_the_command():
    r = subprocess.run([sys.executable, "-m", "pointflow", "--version"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.startswith("pointflow "), r.stdout + r.stderr
