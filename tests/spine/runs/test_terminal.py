"""What a new user sees of ``pointflow run`` (issue 31.7): a line at once before the stages start,
log lines and the live progress line that do not overwrite each other on a terminal (a real
pseudo-terminal here, its output replayed through a small terminal model), evictions on the
progress line and a warning when a file overruns the ring, ``pointflow --version``."""
from __future__ import annotations

import json
import os
import pty
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from pointflow import __version__

REPO = Path(__file__).resolve().parents[3]
LOG_LINE = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} \S+ (DEBUG|INFO|WARNING|ERROR) ")


def _env() -> dict:
    return dict(os.environ, PYTHONPATH=str(REPO))


def screen(raw: str) -> list[str]:
    """The lines a terminal shows for ``raw``: ``\\r`` returns to column 0, ``ESC[K`` erases
    to the end of the line, ``\\n`` ends it, other characters overwrite what is there."""
    lines, cur, col, i = [], [], 0, 0
    while i < len(raw):
        c = raw[i]
        if raw.startswith("\x1b[K", i):
            del cur[col:]
            i += 3
            continue
        if c == "\r":
            col = 0
        elif c == "\n":
            lines.append("".join(cur))
            cur, col = [], 0
        else:
            if col < len(cur):
                cur[col] = c
            else:
                cur.append(c)
            col += 1
        i += 1
    if cur:
        lines.append("".join(cur))
    return lines


def _file_cfg(tmp: Path, n: int, ring: int, **file_opts) -> str:
    rng = np.random.default_rng(0)
    np.save(tmp / "big.npy", np.column_stack([rng.normal(size=(n, 3)), rng.random(n)]).astype(np.float32))
    cfg = {"name": "big-file",
           "source": {"transport": "file", "options": {"path": str(tmp / "big.npy"), "chunk_points": 10_000,
                                                      **file_opts}},
           "ring": {"max_points": ring},
           "render": {"backend": "cpu", "size": [64, 48], "output": {"dir": str(tmp / "out"), "every_n_frames": 10}},
           # the subject is what the terminal shows, not liveness: a finished source judged hung
           # at load 25 (issue 31.8, elsewhere) must not fail these runs
           "supervisor": {"max_restarts": 0, "hung_after_ms": 30_000}}
    (tmp / "c.yaml").write_text(json.dumps(cfg))
    return str(tmp / "c.yaml")


def test_log_lines_and_the_progress_line_do_not_overwrite_each_other_on_a_terminal(tmp_path):
    # a stream paced over ~3 s: log lines (the overrun warning from the source process, "source
    # finished" from the supervisor) arrive while the progress line is drawn every 0.5 s
    cfg = _file_cfg(tmp_path, 300_000, 100_000, points_per_second=100_000)
    master, slave = pty.openpty()
    p = subprocess.Popen([sys.executable, "-m", "pointflow.cli", "run", cfg, "--duration", "120"],
                         stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=slave, env=_env(), cwd=tmp_path)
    os.close(slave)
    raw = b""
    end = time.monotonic() + 150
    stopped = False
    while time.monotonic() < end:
        try:
            data = os.read(master, 65536)
        except OSError:  # EIO: every writer of the terminal is gone
            break
        if not data:
            break
        raw += data
        if not stopped and b"source finished" in raw and b"evicted=200.0k" in raw:
            time.sleep(1.0)  # a progress line or two more
            p.send_signal(signal.SIGINT)  # as Ctrl-C
            stopped = True
    os.close(master)
    out = p.communicate(timeout=60)[0].decode()
    assert p.returncode == 0, raw.decode(errors="replace")[-3000:]
    text = raw.decode(errors="replace").replace("\r\n", "\n")  # the pty's own newline translation
    lines = screen(text)
    assert lines[0].startswith("starting big-file: 1 source (file), ring 100,000 points"), lines[:3]
    logs = [ln for ln in lines if " INFO " in ln or " WARNING " in ln]
    assert any("more than the ring holds" in ln for ln in logs), lines
    assert any("source finished" in ln for ln in logs), lines
    for ln in logs:  # each log line whole, on its own line: no progress text before or inside it
        assert LOG_LINE.match(ln), ln
        assert "cpu[" not in ln and " frames=" not in ln, ln
    progress = [ln for ln in lines if ln.startswith("t=")]
    assert progress, lines
    for ln in progress:  # and no log text inside a progress line
        assert " INFO " not in ln and " WARNING " not in ln, ln
    assert "evicted=200.0k" in out, out  # the summary (stdout): 300k points through a 100k ring


def test_evictions_are_on_the_progress_line_and_a_file_overrun_is_said_once(tmp_path):
    cfg = _file_cfg(tmp_path, 300_000, 100_000, realtime=False)
    p = subprocess.Popen([sys.executable, "-m", "pointflow.cli", "run", cfg, "--duration", "120"], text=True,
                         stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env(), cwd=tmp_path)
    err, sent = [], False
    for line in p.stderr:  # until a progress line (every 5 s off a terminal) shows the evictions, then Ctrl-C
        err.append(line)
        if line.startswith("t=") and "evicted=200.0k" in line and not sent:
            p.send_signal(signal.SIGINT)
            sent = True
    out = p.communicate(timeout=120)[0]
    stderr = "".join(err)
    assert p.returncode == 0, stderr[-3000:]
    assert stderr.startswith("starting big-file: "), stderr[:500]  # printed before anything starts
    summary = out.splitlines()[0]
    assert "evicted=200.0k" in summary and "source=100% of 300.0k" in summary, summary
    said = [ln for ln in stderr.splitlines() if "more than the ring holds" in ln]
    assert len(said) == 1 and " WARNING " in said[0], said
    assert "of its 300,000 points only the last 100,000 stay in view" in said[0], said[0]
    assert "`map: {path: " in said[0] and "docs/map.md" in said[0], said[0]
    stats = json.loads((tmp_path / "out" / "stats.json").read_text())
    assert stats["stages"]["ingest"]["ring_evicted"] == 200_000


def test_version():
    r = subprocess.run([sys.executable, "-m", "pointflow.cli", "--version"], capture_output=True, text=True,
                       timeout=60, env=_env())
    assert r.returncode == 0 and r.stdout.startswith(f"pointflow {__version__} (Python "), (r.stdout, r.stderr)


def test_the_standby_render_says_it_is_the_standby(tmp_path):
    """The spare render stage prepared beside the running one (supervisor.standby) logs its
    tier selection and warm-up as ``render-standby[pid]``, after a line saying what it is, so
    they do not read like a restart (issue 40); the running stage's lines say ``render[pid]``."""
    cfg = {"name": "standby-words", "source": {"transport": "synthetic", "options": {"scan_hz": 5, "points_per_scan": 500}},
           "ring": {"max_points": 10_000}, "render": {"backend": "cpu", "size": [64, 48], "output": {"dir": None}},
           "tracing": {"enabled": False}, "supervisor": {"standby": True}}
    (tmp_path / "c.yaml").write_text(json.dumps(cfg))
    p = subprocess.Popen([sys.executable, "-m", "pointflow.cli", "run", str(tmp_path / "c.yaml"), "--duration", "200"],
                         text=True, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         env=_env(), cwd=tmp_path)
    err, sent = [], False
    for line in p.stderr:  # until the standby has drawn its warm-up frame, then Ctrl-C
        err.append(line)
        if "render-standby[" in line and "warm-up frame drawn" in line and not sent:
            p.send_signal(signal.SIGINT)
            sent = True
    p.communicate(timeout=120)
    stderr = "".join(err)
    assert p.returncode == 0 and sent, stderr[-3000:]
    standby = [ln for ln in stderr.splitlines() if "render-standby[" in ln]
    running = [ln for ln in stderr.splitlines() if " render[" in ln]
    assert "preparing a standby: a spare render" in standby[0], standby
    assert any("tier selection: cpu: chosen" in ln for ln in standby), standby
    assert sum("tier selection: cpu: chosen" in ln for ln in running) == 1, running  # the first start only
    assert len({ln.split("[")[1].split("]")[0] for ln in standby}) == 1  # one process: the spare
    for ln in standby + running:
        assert LOG_LINE.match(ln), ln


def test_an_activated_standby_logs_as_the_stage():
    """Once activated, the standby's lines name the stage again (``render[pid]``): from then
    on it is the render stage, and its errors must read so."""
    code = ("import logging, types\n"
            "from pointflow.runtime.stage import _setup_logging\n"
            "info = types.SimpleNamespace(log_level=logging.INFO)\n"
            "_setup_logging('render', info, standby=True); logging.getLogger('x').info('prepared')\n"
            "_setup_logging('render', info); logging.getLogger('x').info('activated')\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=_env())
    lines = r.stderr.splitlines()
    assert r.returncode == 0 and len(lines) == 2, r.stderr
    assert " render-standby[" in lines[0] and lines[0].endswith(" INFO prepared"), lines
    assert " render[" in lines[1] and lines[1].endswith(" INFO activated"), lines
    assert all(LOG_LINE.match(ln) for ln in lines), lines
