"""Suite-wide set-up: a private XDG_RUNTIME_DIR (silences wgpu/Mesa warnings, holds ipc:// sockets)."""
import os
import tempfile

if not os.environ.get("XDG_RUNTIME_DIR"):
    d = os.path.join(tempfile.gettempdir(), f"pointflow-xdg-{os.getuid()}")
    os.makedirs(d, mode=0o700, exist_ok=True)
    os.environ["XDG_RUNTIME_DIR"] = d


def pytest_sessionstart(session):
    """Compile pointflow's numba loops once, into numba's disk cache (``pointflow warm``): a
    stage whose loops are not cached draws (or places points) without them while a compiler
    fills the cache beside it, and the tests of the compiled paths want them from the start.
    ~20 s the first time on a machine, a fraction of a second after."""
    try:
        from pointflow.jitcache import warm_all

        warm_all(lambda line: None)
    except Exception:  # noqa: BLE001 - no numba: the reference tier draws, nothing to warm
        pass
