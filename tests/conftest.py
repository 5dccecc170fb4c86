"""Suite-wide set-up: a private XDG_RUNTIME_DIR (silences wgpu/Mesa warnings, holds ipc:// sockets)."""
import os
import tempfile

if not os.environ.get("XDG_RUNTIME_DIR"):
    d = os.path.join(tempfile.gettempdir(), f"pointflow-xdg-{os.getuid()}")
    os.makedirs(d, mode=0o700, exist_ok=True)
    os.environ["XDG_RUNTIME_DIR"] = d


def pytest_sessionstart(session):
    """Compile the cpu tier's numba loops once, into numba's disk cache: on a fresh clone a
    render stage choosing the compiled cpu raster (``backend: auto`` over a software adapter)
    would otherwise compile them inside its start-up grace period; later loads take ~0.5 s."""
    try:
        from pointflow.render import cpu_kernels

        cpu_kernels.load()
    except Exception:  # noqa: BLE001 - no numba: the reference tier draws, nothing to warm
        pass
