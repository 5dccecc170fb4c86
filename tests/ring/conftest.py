import os
import time

import pytest

os.environ.setdefault("XDG_RUNTIME_DIR", "/tmp/xdg")

# owner pid offsets in the segment headers (see pointflow/ring/ring.py and slabs.py)
_RING_OWNER_OFF = 64 + 8 * 15
_SLAB_OWNER_OFF = 64 + 8 * 8


def ring_segments() -> set[str]:
    """Our segments in /dev/shm (other packages' tests may create theirs concurrently)."""
    return {n for n in os.listdir("/dev/shm") if n.startswith(("pfring_", "pfslab_"))}


def _owner_pid(name: str) -> int | None:
    off = _RING_OWNER_OFF if name.startswith("pfring_") else _SLAB_OWNER_OFF
    try:
        with open("/dev/shm/" + name, "rb") as f:
            f.seek(off)
            return int.from_bytes(f.read(8), "little")
    except OSError:
        return None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
        return True
    except ProcessLookupError:
        return False
    except PermissionError:
        return True


def _suspects(before: set[str]) -> list[str]:
    out = []
    for n in ring_segments() - before:
        pid = _owner_pid(n)
        if pid is None:
            continue  # vanished meanwhile
        if pid == os.getpid() or pid == 0 or not _alive(pid):
            out.append(n)
    return sorted(out)


def leaked_since(before: set[str], settle_s: float = 5.0) -> list[str]:
    """New segments owned by this process or by a process that no longer exists.

    Segments of other live processes (the other xdist worker, other engineers' runs) are ignored.
    A suspect must stay one for ``settle_s``: a ring another process is still building reads
    owner pid 0 until its header is written (a 4M-point ring takes a while to fill with NaN), and
    a killed pipeline's segments stay until its stages or the next supervisor sweep them.
    """
    deadline = time.monotonic() + settle_s
    while True:
        out = _suspects(before)
        if not out or time.monotonic() >= deadline:
            return out
        time.sleep(0.1)


@pytest.fixture(autouse=True)
def no_leaked_segments():
    before = ring_segments()
    yield
    import gc

    gc.collect()
    leaked = leaked_since(before)
    assert not leaked, f"leaked shared-memory segments: {leaked}"
