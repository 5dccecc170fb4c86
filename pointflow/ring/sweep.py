"""Remove segments left behind by a pipeline whose owner process was killed.

The supervisor unlinks its segments on every exit path it gets to run. When it is killed
outright (SIGKILL, or SIGTERM to a Python process without a handler) nothing runs in it,
so the stages — which get SIGTERM from the kernel when it dies — sweep on their way out,
and every new supervisor sweeps at start. A segment is removed only when it is ours (same
uid), is a pointflow ring or slab (magic), and its owner pid no longer exists.
"""
from __future__ import annotations

import os

from .layout import SHM_DIR
from .ring import I_OWNER_PID, MAGIC, STATE_OFF
from .slabs import _S_STATE_OFF, S_OWNER_PID, SLAB_MAGIC

PREFIXES = ("pfring_", "pfslab_")


def pid_alive(pid: int) -> bool:
    """True while ``pid`` exists (someone else's process counts as alive)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def owner_pid(path: str) -> int | None:
    """The pid recorded in a ring or slab header, or None when it is not one of ours."""
    with open(path, "rb") as f:
        head = f.read(STATE_OFF + 8 * 32)
    if head[:8] == MAGIC:
        off = STATE_OFF + 8 * I_OWNER_PID
    elif head[:8] == SLAB_MAGIC:
        off = _S_STATE_OFF + 8 * S_OWNER_PID
    else:
        return None
    if len(head) < off + 8:
        return None
    return int.from_bytes(head[off:off + 8], "little", signed=True)


def sweep_orphans(shm_dir: str = SHM_DIR) -> list[str]:
    """Unlink our pointflow segments whose owner process is gone; returns their names."""
    removed: list[str] = []
    try:
        names = os.listdir(shm_dir)
    except FileNotFoundError:
        return removed
    uid = os.getuid()
    for name in names:
        if not name.startswith(PREFIXES):
            continue
        path = os.path.join(shm_dir, name)
        try:
            if os.stat(path).st_uid != uid:
                continue
            pid = owner_pid(path)
            if pid is not None and pid > 0 and not pid_alive(pid):
                os.unlink(path)
                removed.append(name)
        except (FileNotFoundError, PermissionError):
            continue  # unlinked meanwhile, or not readable: not ours to judge
    return removed
