"""Suite-wide set-up: a private XDG_RUNTIME_DIR (silences wgpu/Mesa warnings, holds ipc:// sockets)."""
import os
import tempfile

if not os.environ.get("XDG_RUNTIME_DIR"):
    d = os.path.join(tempfile.gettempdir(), f"pointflow-xdg-{os.getuid()}")
    os.makedirs(d, mode=0o700, exist_ok=True)
    os.environ["XDG_RUNTIME_DIR"] = d
