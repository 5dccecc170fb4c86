"""End to end: real processes, real ZeroMQ, real shared memory; clean stops however a run ends."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml
import zmq

from pointflow import Pipeline, wire
from pointflow.chunk import PointChunk, new_trace_id
from pointflow.runtime.supervisor import PipelineFailed

from ..helpers import assert_gone, assert_segments_gone, free_tcp_port, small_config, wait_for

STAGES = {"source", "ingest", "cadence", "render"}


def _frames_done(pipe) -> bool:
    return pipe.stats().get("frames", 0) >= 6


def test_full_run_produces_frames_and_stats(tmp_path):
    out = tmp_path / "out"
    pipe = Pipeline.from_dict(small_config(), out_dir=str(out))
    with pipe:
        pipe.wait(60, until=lambda: _frames_done(pipe))
        live = pipe.stats()
        pids = [s["pid"] for s in live["stages"].values()]
    stats = json.loads((out / "stats.json").read_text())
    assert set(stats["stages"]) == STAGES
    assert len({s["pid"] for s in stats["stages"].values()}) == 4, "each stage is its own process"
    for name in ("ingest", "cadence", "render"):
        assert stats["stages"][name]["points_in"] > 0, name
    assert stats["stages"]["source"]["points_out"] > 0
    assert stats["frames"] >= 6
    for key in ("pid", "points_in", "points_out", "drops", "cpu_percent", "rss_bytes"):
        assert all(key in s for s in stats["stages"].values()), key
    pngs = sorted(out.glob("frame_*.png"))
    assert pngs, "no PNG frames written"
    from PIL import Image

    img = np.asarray(Image.open(pngs[-1]))
    assert img.shape == (120, 160, 4)
    bg = img[0, 0]
    assert (np.abs(img.astype(int) - bg.astype(int)).sum(axis=2) > 30).mean() > 0.02, "frame shows no points"
    # ingest accounting agrees with the ring
    ing = stats["stages"]["ingest"]
    assert stats["ring"]["total_written"] == ing["points_out"]
    acc = stats["accounting"]
    assert acc["ingest_balanced"] and acc["ring_agrees"]
    assert acc["lost_before_ingest"] == 0, "a clean stop delivers every point the source sent"
    assert_gone(pids)
    assert_segments_gone(stats)


def _cli_run(tmp_path, extra_cfg=None, **over):
    cfg = small_config(**over)
    if extra_cfg:
        cfg.update(extra_cfg)
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(cfg))
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "pointflow.cli", "run", str(path), "--out", str(out), "-q"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True, text=True)
    return proc, out


def _stage_pids(proc) -> list[int]:
    kids = [c for c in _children(proc.pid)]
    return [c.pid for c in kids]


def _children(pid):
    import psutil

    try:
        return [c for c in psutil.Process(pid).children(recursive=True) if "resource_tracker" not in " ".join(c.cmdline())]
    except psutil.Error:
        return []


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_cli_stops_cleanly_on_signal(tmp_path, sig):
    proc, out = _cli_run(tmp_path)
    try:
        assert wait_for(lambda: list(out.glob("frame_*.png")), timeout=60), "no frame before the signal"
        pids = _stage_pids(proc)
        assert len(pids) >= 4
        if sig == signal.SIGINT:
            os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C reaches the whole process group
        else:
            os.kill(proc.pid, signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 0, err[-2000:]
    assert_gone(pids)
    stats = json.loads((out / "stats.json").read_text())
    assert stats["frames"] > 0
    assert_segments_gone(stats)


def test_sigkill_of_a_stage_stops_everything_cleanly(tmp_path):
    """With no restarts allowed, a killed stage ends the run: non-zero exit, no leftovers."""
    proc, out = _cli_run(tmp_path)
    try:
        assert wait_for(lambda: list(out.glob("frame_*.png")), timeout=60)
        pids = _stage_pids(proc)
        os.kill(pids[0], signal.SIGKILL)  # any stage: the first spawned is render
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 2, err[-2000:]
    assert "restart limit 0 reached" in err
    assert_gone(pids)
    assert_segments_gone(json.loads((out / "stats.json").read_text()))


def test_pipeline_api_reports_a_killed_stage(tmp_path):
    """With no restarts allowed, a killed stage fails the run with PipelineFailed naming it.
    On a loaded machine the supervision thread may see the death later, never not at all:
    wait() raises as soon as it does (up to 120 s here)."""
    pipe = Pipeline.from_dict(small_config(), out_dir=str(tmp_path))
    pipe.start()
    try:
        pipe.wait(120, until=lambda: pipe.stats()["frames"] > 0)
        pids = [s["pid"] for s in pipe.stats()["stages"].values()]
        os.kill(pipe.stats()["stages"]["cadence"]["pid"], signal.SIGKILL)
        with pytest.raises(PipelineFailed, match="cadence.*SIGKILL"):
            pipe.wait(120)
    finally:
        stats = pipe.stop()
    assert stats["events"][0]["stage"] == "cadence"
    assert_gone(pids)
    assert_segments_gone(stats)


def test_external_source_over_tcp(tmp_path):
    """A source on another machine: it connects to ingest's tcp:// endpoint and sends chunks."""
    port = free_tcp_port()
    cfg = small_config(endpoints={"ingest": f"tcp://127.0.0.1:{port}"})
    cfg["sources"] = [{**cfg.pop("source"), "name": "synth"}, {"transport": "zmq", "name": "remote", "external": True}]
    cfg["sources"][0]["options"].update(points_per_scan=1000, scans=2)
    pipe = Pipeline.from_dict(cfg, out_dir=str(tmp_path))
    ctx = zmq.Context()
    push = ctx.socket(zmq.PUSH)
    push.setsockopt(zmq.LINGER, 1000)
    try:
        s = _send_remote(pipe, push, port)
    finally:
        push.close(0)
        ctx.term()
    assert s["synth"]["points_out"] > 0
    assert s["ingest"]["points_in"] == 20 * 500 + s["synth"]["points_out"]
    assert "remote" not in s, "an external source is not started by the supervisor"


def _send_remote(pipe, push, port) -> dict:
    with pipe:
        pipe.wait(30, until=lambda: pipe.stats()["stages"]["ingest"]["points_in"] > 0)
        push.connect(f"tcp://127.0.0.1:{port}")
        n_sent = 0
        for i in range(20):
            pos = np.random.default_rng(i).normal(size=(500, 3)) + [6.4e5, 4.9e6, 0]
            wire.send(push, PointChunk(positions=pos, channels={"intensity": np.ones(500, np.float32)},
                                       source_id="remote", seq=i, trace_id=new_trace_id(), t_sent_ns=time.monotonic_ns()))
            n_sent += 500
        synthetic_sent = lambda: pipe.stats()["stages"]["synth"]["points_out"]
        pipe.wait(20, until=lambda: pipe.stats()["stages"]["synth"]["finished"]
                  and pipe.stats()["stages"]["ingest"]["points_in"] >= n_sent + synthetic_sent())
    return pipe.stats()["stages"]


def test_an_out_dir_that_is_a_file_is_a_config_error_once(tmp_path):
    """Pipeline(out_dir=<a file>).start(): one ConfigError naming it, nothing started, and
    no traceback at exit (it raised FileExistsError from start and stop, then at exit)."""
    import subprocess
    import sys

    (tmp_path / "afile").write_text("x")
    p = subprocess.run([sys.executable, "-c", (
        "from pointflow import Pipeline\n"
        "from pointflow.typed import ConfigError\n"
        "p = Pipeline.from_dict({}, out_dir='afile')\n"
        "try:\n    p.start()\nexcept ConfigError as e:\n    print('REFUSED', e)\n"
        "print('STOP', p.stop())\n")], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr[-2000:]
    assert f"REFUSED output directory {tmp_path / 'afile'}: exists and is not a directory" in p.stdout, p.stdout
    assert "STOP" in p.stdout and "Traceback" not in p.stderr and "Exception ignored" not in p.stderr, p.stderr


def test_bare_xyz_under_the_default_colouring_is_not_warned_of(tmp_path):
    """Pipeline() and send(xyz): the default color_by (intensity) missing from the points is
    said at info, not as a WARNING on every run (docs/api.md's first example warned)."""
    import subprocess
    import sys

    p = subprocess.run([sys.executable, "-c", (
        "import numpy as np\n"
        "from pointflow import Pipeline\n"
        "with Pipeline.from_dict({}, out_dir='') as p:\n"
        "    p.send(np.zeros((100, 3), np.float32))\n"
        "    p.wait(60, until=lambda: p.stats()['stages']['ingest']['points_out'] >= 100)\n")],
        cwd=tmp_path, capture_output=True, text=True, timeout=180)
    assert p.returncode == 0, p.stderr[-2000:]
    assert "WARNING render.color_by" not in p.stderr, p.stderr[-2000:]


def test_durations_are_checked_and_wait_needs_a_start():
    """run(-5) and run(nan) ran, wait(-1) returned False, and wait() before start() returned
    False where stats() and send() raise: as `pointflow run --duration` refuses them."""
    from pointflow import Pipeline

    p = Pipeline.from_dict({}, out_dir="")
    for bad in (-5, float("nan"), float("inf"), "10", True):
        with pytest.raises(ValueError, match="duration_s: expected a number of seconds >= 0 or None"):
            p.run(bad)
        with pytest.raises(ValueError, match="duration_s"):
            p.wait(bad)
    with pytest.raises(RuntimeError, match=r"call start\(\) first"):
        p.wait(1)
    assert not p.running
