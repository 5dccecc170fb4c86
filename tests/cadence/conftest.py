import os

import pytest

os.environ.setdefault("XDG_RUNTIME_DIR", "/tmp/xdg")
os.makedirs(os.environ["XDG_RUNTIME_DIR"], exist_ok=True)


def _segments() -> set[str]:
    return {n for n in os.listdir("/dev/shm") if n.startswith(("pfring_", "pfslab_"))}


@pytest.fixture(autouse=True)
def no_leaked_segments():
    before = _segments()
    yield
    import gc

    gc.collect()
    leaked = _segments() - before
    assert not leaked, f"leaked shared-memory segments: {sorted(leaked)}"
