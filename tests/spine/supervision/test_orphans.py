"""A supervisor killed outright cannot clean up; its stages (SIGTERM from the kernel via
PR_SET_PDEATHSIG) and the next supervisor remove what it left."""
from __future__ import annotations

import multiprocessing as mp
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import yaml

from pointflow.ring import PointRing
from pointflow.ring.sweep import sweep_orphans

from ..helpers import assert_gone, small_config, wait_for

SHM = "/dev/shm"


def _make_ring_and_die(conn) -> None:
    r = PointRing(1000, channels=["intensity"])
    conn.send(r.name)  # synchronous, unlike a Queue's feeder thread
    os.kill(os.getpid(), signal.SIGKILL)


def test_sweep_removes_only_segments_of_dead_owners():
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    p = ctx.Process(target=_make_ring_and_die, args=(child,))
    p.start()
    assert parent.poll(60), "the child did not report its ring"
    dead_name = parent.recv()
    p.join(30)
    assert p.exitcode == -signal.SIGKILL
    assert os.path.exists(os.path.join(SHM, dead_name)), "a SIGKILLed owner leaves its segment"
    with PointRing(10) as alive:
        removed = sweep_orphans()
        assert dead_name in removed
        assert alive.name not in removed and os.path.exists(os.path.join(SHM, alive.name))
    assert not os.path.exists(os.path.join(SHM, dead_name))


def test_sigkill_of_the_supervisor_leaves_nothing(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(small_config()))
    out = tmp_path / "out"
    # the supervisor's run directory of ipc:// sockets goes here (a short path: a socket path
    # has at most 107 bytes)
    xdg = Path(tempfile.mkdtemp(prefix="pfx"))
    proc = subprocess.Popen([sys.executable, "-m", "pointflow.cli", "run", str(path), "--out", str(out), "-q"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            env=dict(os.environ, XDG_RUNTIME_DIR=str(xdg)))
    lines = []
    try:
        for line in proc.stderr:  # the supervisor logs its segment names at start
            lines.append(line)
            if "ring pfring_" in line:
                break
        assert wait_for(lambda: list(out.glob("frame_*.png")), timeout=120), "no frame before the kill"
        import psutil

        kids = [c.pid for c in psutil.Process(proc.pid).children(recursive=True)]
        run_dirs = list(xdg.glob(f"pointflow-{proc.pid}-*"))
        assert len(run_dirs) == 1 and list(run_dirs[0].iterdir()), "no run directory with sockets"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.stderr.close()
    m = re.search(r"ring (pfring_\w+):.*slabs (pfslab_\w+) (pfslab_\w+)", "".join(lines))
    assert m, "segment names not logged"
    assert_gone(kids)  # stages saw their supervisor die and exited
    # the stages remove them as they stop: seconds on a loaded machine, so long waits
    assert wait_for(lambda: not any(os.path.exists(os.path.join(SHM, n)) for n in m.groups()), timeout=60), \
        "segments of a killed supervisor were not removed"
    # issue 14.4: the stages also removed the run directory of ipc:// sockets
    assert wait_for(lambda: not run_dirs[0].exists(), timeout=60), "run directory of a killed supervisor stays"
    xdg.rmdir()


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_new_supervisor_sweeps_run_dirs_of_dead_supervisors(tmp_path, monkeypatch):
    from pointflow.runtime.pipeline import Pipeline

    xdg = Path(tempfile.mkdtemp(prefix="pfx"))
    dead = xdg / f"pointflow-{_dead_pid()}-0123abcd"
    live = xdg / f"pointflow-{os.getppid()}-89abcdef"   # its supervisor (our parent) is alive
    other = xdg / "pointflow-notarun"                    # not a run directory name
    for d in (dead, live, other):
        d.mkdir()
        (d / "control").write_text("")  # stands for a socket file left behind
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(xdg))
    pipe = Pipeline.from_dict(small_config(), out_dir=str(tmp_path / "out"))
    pipe.start()
    try:
        assert not dead.exists(), "a new supervisor keeps the run directory of a dead one"
        assert live.exists() and other.exists()
    finally:
        pipe.stop()
    assert sorted(p.name for p in xdg.iterdir()) == sorted([live.name, other.name])  # its own went too
    shutil.rmtree(xdg)
