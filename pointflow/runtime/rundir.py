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
import stat
import tempfile
from dataclasses import asdict

from ..ring.sweep import pid_alive
from ..typed import ConfigError

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


def _usable_runtime_dir(path: str | None) -> bool:
    """What the graphics stack (libwayland, Mesa's EGL/Vulkan WSI) accepts as
    ``XDG_RUNTIME_DIR``: an existing directory of ours that only we can enter."""
    if not path or not os.path.isabs(path):
        return False
    try:
        st = os.stat(path)
    except OSError:
        return False
    return stat.S_ISDIR(st.st_mode) and st.st_uid == os.getuid() and not (st.st_mode & 0o077)


def ensure_runtime_dir() -> str | None:
    """Give this process (and the stages it starts) a valid ``XDG_RUNTIME_DIR``.

    A shell without one (ssh, containers, cron) makes the graphics libraries print
    ``error: XDG_RUNTIME_DIR is invalid or not set in the environment.`` once per probe;
    with an unset or unusable value, use a private ``/tmp/pointflow-xdg-<uid>`` (mode 0700,
    ours, not a symlink) instead. Must run before any graphics library is imported.
    Returns the directory set here, or None when the environment's was kept."""
    if _usable_runtime_dir(os.environ.get("XDG_RUNTIME_DIR")):
        return None
    path = os.path.join(tempfile.gettempdir(), f"pointflow-xdg-{os.getuid()}")
    try:
        os.mkdir(path, 0o700)
    except FileExistsError:
        pass
    except OSError:
        return None
    try:
        st = os.lstat(path)
    except OSError:
        return None
    if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.getuid():
        return None  # someone else's (or a symlink): leave the environment as it was
    if st.st_mode & 0o077:
        os.chmod(path, 0o700)
    os.environ["XDG_RUNTIME_DIR"] = path
    return path


#: sizeof(sockaddr_un.sun_path) - 1 on Linux: the longest ipc:// path ZeroMQ can bind.
IPC_PATH_MAX = 107


def check_socket_paths(endpoints) -> None:
    """ConfigError naming the endpoint whose ``ipc://`` socket path is too long to bind."""
    for key, ep in asdict(endpoints).items():
        sock = ep[len("ipc://"):] if isinstance(ep, str) and ep.startswith("ipc://") else ""
        if len(sock.encode()) > IPC_PATH_MAX:
            raise ConfigError(f"endpoints.{key}", f"socket path {sock} has {len(sock.encode())} bytes, a Unix "
                                                  f"socket allows {IPC_PATH_MAX}; set XDG_RUNTIME_DIR (or the "
                                                  "endpoint) to a shorter path")
