"""A ring that cannot fit in /dev/shm is refused before any stage starts (issue 14.3)."""
from __future__ import annotations

import os
import subprocess
import sys

import yaml

from pointflow.ring import RingLayout
from pointflow.ring.space import RingSpaceError, check_shm_space, shm_bytes, shm_free
from pointflow.ring.sweep import owner_pid

from ..helpers import SHM, shm_names, small_config


def _too_many_points() -> int:
    return shm_free() // 12 + 1  # positions alone (12 B a point) in three segments exceed what is free


def test_check_says_bytes_needed_and_free():
    n = _too_many_points()
    layout = RingLayout(n)
    try:
        check_shm_space(layout)
    except RingSpaceError as exc:
        assert exc.need == shm_bytes(layout) > exc.free > 0
        msg = str(exc)
        assert f"{exc.need:,} bytes" in msg and f"{SHM} has {exc.free:,} bytes free" in msg and "ring.max_points" in msg
    else:
        raise AssertionError("a ring larger than /dev/shm passed the check")
    assert check_shm_space(RingLayout(1000)) == shm_bytes(RingLayout(1000))


def test_run_with_a_ring_larger_than_shm_is_a_config_error(tmp_path):
    cfg = small_config(ring={"max_points": _too_many_points()})
    path = tmp_path / "big.yaml"
    path.write_text(yaml.safe_dump(cfg))
    xdg = tmp_path / "xdg"
    xdg.mkdir(mode=0o700)
    before = shm_names()
    proc = subprocess.Popen([sys.executable, "-m", "pointflow.cli", "run", str(path), "--duration", "2", "-q",
                             "--out", str(tmp_path / "out")], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=dict(os.environ, XDG_RUNTIME_DIR=str(xdg)))
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 1, stderr
    assert "Traceback" not in stderr
    err = [ln for ln in stderr.splitlines() if "config error" in ln]
    assert len(err) == 1 and "ring.max_points" in err[0] and "bytes free" in err[0] and "need" in err[0], stderr
    assert "tier selection" not in stderr  # no stage ran
    assert list(xdg.iterdir()) == []  # no run directory left
    assert not [n for n in shm_names() - before if _owner(n) == proc.pid]  # no segment of this run


def _owner(name: str):
    try:
        return owner_pid(os.path.join(SHM, name))
    except OSError:
        return None


def test_socket_path_too_long_is_a_config_error(tmp_path):
    """XDG_RUNTIME_DIR so deep that a socket path passes the 107 bytes of sun_path: refused
    at start with the reason, instead of every stage failing to bind."""
    deep = tmp_path / ("d" * 60)
    deep.mkdir(mode=0o700)
    path = tmp_path / "ok.yaml"
    path.write_text(yaml.safe_dump(small_config()))
    r = subprocess.run([sys.executable, "-m", "pointflow.cli", "run", str(path), "--duration", "2", "-q",
                        "--out", str(tmp_path / "out")], capture_output=True, text=True, timeout=120,
                       env=dict(os.environ, XDG_RUNTIME_DIR=str(deep)))
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr
    assert "a Unix socket allows 107" in r.stderr and "XDG_RUNTIME_DIR" in r.stderr
    assert list(deep.iterdir()) == []  # the run directory was removed
