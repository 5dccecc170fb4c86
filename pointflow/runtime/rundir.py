"""Socket directories of supervisors that were killed.

Each supervisor keeps its ``ipc://`` sockets in ``$XDG_RUNTIME_DIR/pointflow-<pid>-<hex>``
(:func:`pointflow.config.new_run_dir`) and removes it on every exit path it gets to run.
Killed outright (SIGKILL) it cannot: then its stages remove it on their way out (they get
SIGTERM from the kernel), as they remove its shared-memory segments
(:mod:`pointflow.ring.sweep`), and every new supervisor removes the directories whose
owner pid is gone.
"""
from __future__ import annotations

import os
import re
import shutil
import tempfile

from ..ring.sweep import pid_alive

#: The names :func:`pointflow.config.new_run_dir` gives; group 1 is the supervisor's pid.
RUN_DIR_RE = re.compile(r"pointflow-(\d+)-[0-9a-f]{8}")


def runtime_root() -> str:
    """Where run directories are made (the same rule as ``new_run_dir``)."""
    return os.environ.get("XDG_RUNTIME_DIR") or tempfile.gettempdir()


def owner_pid(path: str) -> int | None:
    """The supervisor pid in a run directory's name, or None when it is not one."""
    m = RUN_DIR_RE.fullmatch(os.path.basename(os.path.normpath(path)))
    return int(m.group(1)) if m else None


def sweep_run_dirs(root: str | None = None) -> list[str]:
    """Remove our run directories under ``root`` whose supervisor is gone; returns their paths."""
    root = root or runtime_root()
    removed: list[str] = []
    try:
        names = os.listdir(root)
    except OSError:
        return removed
    uid = os.getuid()
    for name in names:
        pid = owner_pid(name)
        if pid is None or pid <= 0 or pid == os.getpid():
            continue
        path = os.path.join(root, name)
        try:
            st = os.lstat(path)
        except FileNotFoundError:
            continue
        if st.st_uid != uid or not os.path.isdir(path) or os.path.islink(path) or pid_alive(pid):
            continue
        shutil.rmtree(path, ignore_errors=True)
        if not os.path.exists(path):
            removed.append(path)
    return removed


def remove_orphaned_run_dir(run_dir: str, supervisor_pid: int) -> bool:
    """A stage on its way out: remove its supervisor's run directory if that supervisor is
    dead (never a live supervisor's). True when it was removed here."""
    if not run_dir or owner_pid(run_dir) != supervisor_pid or pid_alive(supervisor_pid):
        return False
    if not os.path.isdir(run_dir):
        return False
    shutil.rmtree(run_dir, ignore_errors=True)
    return not os.path.exists(run_dir)
