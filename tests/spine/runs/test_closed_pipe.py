"""Every command that prints, its output a pipe whose reader already left (``| head -1``,
``| grep -q``, ``| true``): it ends quietly, with no traceback and no "Exception ignored", exit
code 141 (128 + SIGPIPE, what a shell reports for any such writer), and a pipeline it ran is
stopped whole (issue 31.4). The pipe is real: ``os.pipe()`` with its read end closed before the
command starts, so every write the command makes fails with EPIPE."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from pointflow.cli import EXIT_PIPE

from ..helpers import assert_segments_gone, free_tcp_port, small_config

REPO = Path(__file__).resolve().parents[3]


def _closed_pipe() -> int:
    """The write end of a pipe nobody reads any more."""
    r, w = os.pipe()
    os.close(r)
    return w


def _pointflow(args: list[str], cwd: Path, closed: str = "stdout", timeout: float = 120) -> subprocess.CompletedProcess:
    """``pointflow ARGS`` with ``closed`` (stdout or stderr) a closed pipe; the other captured."""
    w = _closed_pipe()
    env = dict(os.environ, PYTHONPATH=str(REPO))
    try:
        io = {"stdout": w, "stderr": subprocess.PIPE} if closed == "stdout" else {"stdout": subprocess.PIPE, "stderr": w}
        return subprocess.run([sys.executable, "-m", "pointflow.cli", *args], cwd=cwd, env=env, timeout=timeout,
                              stdin=subprocess.DEVNULL, **io)
    finally:
        os.close(w)


def _quiet(r, captured: bytes) -> None:
    text = captured.decode(errors="replace")
    assert r.returncode == EXIT_PIPE == 141, (r.returncode, text[-3000:])
    for bad in ("Traceback", "BrokenPipeError", "Exception ignored", "Broken pipe"):
        assert bad not in text, text[-3000:]


def _write(path: Path, cfg: dict) -> str:
    path.write_text(json.dumps(cfg))  # JSON is YAML
    return str(path)


def _mcap(path: Path) -> str:
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        schema = w.register_schema("std_msgs/msg/String", "ros2msg", b"string data")
        ch = w.register_channel("/chatter", "cdr", schema)
        for i in range(3):
            w.add_message(ch, log_time=i * 1000, publish_time=i * 1000, data=b"\x00\x01\x00\x00\x02\x00\x00\x00a\x00")
        w.finish()
    return str(path)


def _commands(tmp: Path) -> dict[str, list[str]]:
    run_cfg = _write(tmp / "run.yaml", small_config(render={"backend": "cpu", "size": [64, 48],
                                                             "output": {"dir": str(tmp / "out"), "every_n_frames": 5}}))
    send_cfg = _write(tmp / "send.yaml", {
        "source": {"transport": "synthetic", "name": "lidar",
                   "options": {"points_per_scan": 2000, "scans": 3, "scan_hz": 20, "chunks_per_scan": 2,
                               "moving_objects": 0}},
        "send": {"endpoint": f"tcp://127.0.0.1:{free_tcp_port()}", "socket": "push", "bind": False}})
    router_cfg = _write(tmp / "router.yaml", {"router": {"listen": [f"tcp/127.0.0.1:{free_tcp_port()}"],
                                                         "scouting": False}})
    return {
        "schema": ["schema"],
        "info": ["info"],
        "validate": ["validate", run_cfg],
        "validate-verbose": ["validate", "--verbose", run_cfg],
        "keys": ["keys", "peer", "--dir", str(tmp / "keys")],
        "inspect": ["inspect", _mcap(tmp / "rec.mcap")],
        "run": ["run", run_cfg, "--duration", "3", "-q"],
        "profile": ["profile", run_cfg, "--duration", "3", "-q"],
        "send": ["send", send_cfg, "--duration", "30", "-q"],
        "router": ["router", router_cfg, "--duration", "2", "-q"],
        "help": ["--help"],
        "version": ["--version"],
    }


@pytest.mark.timeout(180)
@pytest.mark.parametrize("name", ["schema", "info", "validate", "validate-verbose", "keys", "inspect",
                                  "run", "profile", "send", "router", "help", "version"])
def test_a_closed_stdout_ends_every_command_quietly(tmp_path, name):
    if name in ("send", "router"):
        pytest.importorskip("zenoh" if name == "router" else "zmq")
    if name == "inspect":
        pytest.importorskip("mcap")
    r = _pointflow(_commands(tmp_path)[name], tmp_path)
    if name in ("help", "version"):  # argparse swallows the write error itself and exits 0
        assert r.returncode == 0 and r.stderr == b"", (r.returncode, r.stderr)
        return
    _quiet(r, r.stderr)
    if name in ("run", "profile"):  # stopped whole: its stats written, its shared memory gone
        assert_segments_gone(json.loads((tmp_path / "out" / "stats.json").read_text()))


@pytest.mark.timeout(180)
def test_a_run_whose_stderr_reader_leaves_after_one_line_stops(tmp_path):
    """``pointflow run FILE 2>&1 | head -1``: the reader takes the "starting" line and leaves;
    the next progress line finds it gone and the run stops as on Ctrl-C, long before
    ``--duration``, leaving nothing behind."""
    cfg = _write(tmp_path / "run.yaml", small_config(render={"backend": "cpu", "size": [64, 48],
                                                             "output": {"dir": str(tmp_path / "out")}}))
    r, w = os.pipe()
    p = subprocess.Popen([sys.executable, "-m", "pointflow.cli", "run", cfg, "--duration", "100"], cwd=tmp_path,
                         env=dict(os.environ, PYTHONPATH=str(REPO)), stdin=subprocess.DEVNULL,
                         stdout=subprocess.PIPE, stderr=w)
    os.close(w)
    with os.fdopen(r, "rb") as reader:  # head -1
        first = reader.readline()
    out = p.communicate(timeout=120)[0]
    assert first.startswith(b"starting "), first
    _quiet(p, out)
    assert out == b"", out  # nothing printed after the reader left
    stats = json.loads((tmp_path / "out" / "stats.json").read_text())
    assert_segments_gone(stats)
    assert stats["elapsed_s"] < 60, stats["elapsed_s"]  # stopped by the closed pipe, not by --duration


@pytest.mark.timeout(60)
def test_a_closed_stderr_before_the_start_starts_nothing(tmp_path):
    cfg = _write(tmp_path / "run.yaml", small_config(render={"backend": "cpu", "size": [64, 48],
                                                             "output": {"dir": str(tmp_path / "out")}}))
    r = _pointflow(["run", cfg, "--duration", "100"], tmp_path, closed="stderr", timeout=50)
    _quiet(r, r.stdout)
    assert r.stdout == b"" and not (tmp_path / "out" / "stats.json").exists()
