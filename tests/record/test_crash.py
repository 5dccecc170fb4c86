"""Crash safety: after a SIGKILL of the recorder or of the whole pipeline the file reads (with
the ``mcap`` library's streaming reader) up to its last complete chunk, with nothing missing
before it; a restarted recorder writes a new file and overwrites nothing."""
from __future__ import annotations

import os
import signal
import subprocess
import sys

import psutil
import yaml

from pointflow.runtime.pipeline import Pipeline

from .helpers import read_recording, summary_intact, wait_for


def _cfg(rec: str, **record) -> dict:
    return {"source": {"transport": "synthetic", "options": {"scan_hz": 10, "points_per_scan": 20000,
                                                             "chunks_per_scan": 10}},
            "ring": {"max_points": 100_000},
            "render": {"backend": "cpu", "size": [64, 48], "output": {"every_n_frames": 1000}},
            "supervisor": {"max_restarts": 2, "restart_backoff_ms": 100, "hung_after_ms": 10_000},
            # a deep queue: ingest drops no copy while a recorder (re)starts slowly on a loaded machine
            "record": {"path": rec, "chunk_size": 20_000, "flush_s": 0.2, "queue_messages": 1024, **record}}


def _seqs(msgs) -> list[int]:
    return [m.sequence for m in msgs]


def test_sigkill_of_the_recorder_continues_in_a_new_file(tmp_path):
    rec = tmp_path / "rec.mcap"
    with Pipeline.from_dict(_cfg(str(rec)), out_dir=str(tmp_path / "out")) as pipe:
        recorder = lambda: pipe.stats()["stages"]["recorder"]
        pipe.wait(60, until=lambda: recorder().get("record_messages", 0) >= 10)
        before = recorder()["record_messages"]
        os.kill(recorder()["pid"], signal.SIGKILL)
        pipe.wait(60, until=lambda: recorder()["restarts"] == 1 and recorder().get("record_messages", 0) >= before + 10)
        assert recorder()["restarts"] == 1 and recorder()["alive"]
    st = pipe.stats()
    first, second = str(rec), str(tmp_path / "rec.0001.mcap")
    assert sorted(p.name for p in tmp_path.glob("rec*.mcap")) == ["rec.0001.mcap", "rec.mcap"]
    assert not summary_intact(first), "killed before it could write the summary"
    a = read_recording(first, tolerant=True)
    assert len(a) >= before, "everything the recorder reported written is readable"
    assert _seqs(a) == list(range(len(a))), "nothing missing before the cut"
    assert summary_intact(second)
    b = read_recording(second)
    acc = st["accounting"]
    assert b and _seqs(b) == sorted(set(_seqs(b))), "in order, nothing twice"
    if _seqs(b) != list(range(b[0].sequence, b[0].sequence + len(b))):
        assert acc["record_dropped"] > 0, "a gap in the new file is a copy ingest dropped, and counted"
    assert b[0].sequence >= len(a), "nothing recorded twice"
    assert acc["record_tap_balanced"] and acc["recorder_balanced"] and acc["record_covers_ring"]
    assert acc["lost_before_recorder"] is None, "unknown once the recorder was killed"
    assert st["stages"]["recorder"]["record_files"] == 2


def _spawn(tmp_path, rec: str) -> subprocess.Popen:
    cfg = tmp_path / "p.yaml"
    cfg.write_text(yaml.safe_dump(_cfg(rec)))
    log = open(tmp_path / "run.log", "w")
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    p = subprocess.Popen([sys.executable, "-m", "pointflow.cli", "run", str(cfg), "--duration", "120", "-q",
                          "--out", str(tmp_path / "out")], stdout=log, stderr=subprocess.STDOUT, env=env,
                         start_new_session=True)
    log.close()
    return p


def _family(p: subprocess.Popen) -> list[psutil.Process]:
    try:
        return [psutil.Process(p.pid), *psutil.Process(p.pid).children(recursive=True)]
    except psutil.NoSuchProcess:
        return []


def _sweep() -> None:
    """What a supervisor killed outright leaves (every next supervisor sweeps it too)."""
    from pointflow.ring.sweep import sweep_orphans
    from pointflow.runtime.rundir import sweep_run_dirs

    sweep_orphans()
    sweep_run_dirs()


def test_sigkill_of_the_whole_pipeline_leaves_a_readable_file(tmp_path):
    rec = str(tmp_path / "rec.mcap")
    p = _spawn(tmp_path, rec)
    try:
        assert wait_for(lambda: os.path.exists(rec) and os.path.getsize(rec) > 600_000, 90), \
            (tmp_path / "run.log").read_text()[-3000:]
        procs = _family(p)
        os.killpg(p.pid, signal.SIGKILL)  # every process of the run at once: nobody finishes anything
        p.wait(10)
        psutil.wait_procs(procs, timeout=10)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait(10)
        _sweep()
    assert not summary_intact(rec)
    msgs = read_recording(rec, tolerant=True)
    assert len(msgs) >= 8 and _seqs(msgs) == list(range(len(msgs)))
    # pointflow inspect says so, and --recover writes a copy whose summary tools can seek by
    fixed = tmp_path / "fixed.mcap"
    out = subprocess.run([sys.executable, "-m", "pointflow.cli", "inspect", rec, "--recover", str(fixed)],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "summary: MISSING" in out.stdout and f"{len(msgs):,} messages" in out.stdout
    assert summary_intact(str(fixed))
    again = read_recording(str(fixed))
    assert _seqs(again) == _seqs(msgs) and sum(m.n for m in again) == sum(m.n for m in msgs)


def test_sigkill_of_the_supervisor_alone_lets_the_recorder_finish(tmp_path):
    """The stages get SIGTERM when the supervisor dies (PR_SET_PDEATHSIG): the recorder
    drains and writes the summary."""
    rec = str(tmp_path / "rec.mcap")
    p = _spawn(tmp_path, rec)
    try:
        assert wait_for(lambda: os.path.exists(rec) and os.path.getsize(rec) > 300_000, 90), \
            (tmp_path / "run.log").read_text()[-3000:]
        procs = _family(p)
        os.kill(p.pid, signal.SIGKILL)
        p.wait(10)
        gone, alive = psutil.wait_procs(procs, timeout=15)
        assert not alive, alive
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait(10)
        _sweep()
    assert summary_intact(rec)
    msgs = read_recording(rec)
    assert len(msgs) >= 4 and _seqs(msgs) == list(range(len(msgs)))
