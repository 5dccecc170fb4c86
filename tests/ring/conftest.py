import os

import pytest

os.environ.setdefault("XDG_RUNTIME_DIR", "/tmp/xdg")


def ring_segments() -> set[str]:
    """Our segments in /dev/shm (other packages' tests may create theirs concurrently)."""
    return {n for n in os.listdir("/dev/shm") if n.startswith(("pfring_", "pfslab_"))}


@pytest.fixture(autouse=True)
def no_leaked_segments():
    before = ring_segments()
    yield
    import gc

    gc.collect()
    leaked = ring_segments() - before
    assert not leaked, f"leaked shared-memory segments: {sorted(leaked)}"
