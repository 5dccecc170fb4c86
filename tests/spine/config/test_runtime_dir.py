"""Issue 19.8: in a shell without a valid XDG_RUNTIME_DIR (ssh, cron, containers) the CLI
and the stages give themselves a private one before any graphics library loads, so
``pointflow info`` prints its answer and not eight "XDG_RUNTIME_DIR is invalid" lines."""
from __future__ import annotations

import os
import stat
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from pointflow.runtime.rundir import ensure_runtime_dir

MESSAGE = "XDG_RUNTIME_DIR is invalid or not set"


@pytest.mark.parametrize("value", [None, "/nonexistent/xdg", "relative/xdg", "world"])
def test_info_without_a_valid_runtime_dir_prints_no_graphics_errors(tmp_path, value):
    env = {k: v for k, v in os.environ.items() if k != "XDG_RUNTIME_DIR"}
    if value == "world":
        (tmp_path / "open").mkdir(mode=0o755)
        os.chmod(tmp_path / "open", 0o755)
        value = str(tmp_path / "open")
    if value is not None:
        env["XDG_RUNTIME_DIR"] = value
    exe = Path(sys.executable).with_name("pointflow")  # the installed console script
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "pointflow.cli"]
    proc = subprocess.run([*cmd, "info"], env=env, cwd=tmp_path, capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert MESSAGE not in proc.stdout + proc.stderr, (proc.stdout + proc.stderr)[-2000:]
    assert "render backends:" in proc.stdout


def test_ensure_runtime_dir_makes_a_private_one_and_keeps_a_good_one(tmp_path, monkeypatch):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.delenv("XDG_RUNTIME_DIR", raising=False)
    made = ensure_runtime_dir()
    assert made == str(tmp_path / f"pointflow-xdg-{os.getuid()}") == os.environ["XDG_RUNTIME_DIR"]
    st = os.stat(made)
    assert stat.S_ISDIR(st.st_mode) and stat.S_IMODE(st.st_mode) == 0o700 and st.st_uid == os.getuid()
    assert ensure_runtime_dir() is None  # now valid: kept
    good = tmp_path / "mine"
    good.mkdir(mode=0o700)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(good))
    assert ensure_runtime_dir() is None and os.environ["XDG_RUNTIME_DIR"] == str(good)
    # group/world-accessible: the graphics stack refuses it, so it is replaced
    os.chmod(good, 0o755)
    assert ensure_runtime_dir() == made and os.environ["XDG_RUNTIME_DIR"] == made
    # a planted symlink (or someone else's directory) at the private path is not used
    os.rmdir(made)
    os.symlink(str(good), made)
    monkeypatch.setenv("XDG_RUNTIME_DIR", "/nonexistent")
    assert ensure_runtime_dir() is None and os.environ["XDG_RUNTIME_DIR"] == "/nonexistent"
