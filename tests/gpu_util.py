"""Shared test helper: find a wgpu adapter or fail/skip with a reason.

Tests that need a GPU call :func:`require_adapter`. When no adapter exists the test is
skipped with the reason, except under ``POINTFLOW_REQUIRE_GPU=1`` (CI), where it fails,
so a broken GPU stack can never pass silently as "skipped".
"""
from __future__ import annotations

import contextlib
import os
from typing import Any, Optional

import pytest

_CACHE: dict[str, Any] = {}


def gpu_required() -> bool:
    """True when the environment demands a GPU (CI sets POINTFLOW_REQUIRE_GPU=1)."""
    return os.environ.get("POINTFLOW_REQUIRE_GPU", "") not in ("", "0", "false", "no")


def _missing(reason: str):
    if gpu_required():
        pytest.fail(f"POINTFLOW_REQUIRE_GPU=1 but {reason}")
    pytest.skip(reason)


def find_adapter() -> tuple[Optional[Any], str]:
    """(adapter, "") or (None, reason). Prefers the tier's own selection logic so tests
    run on the adapter the renderer would pick (lavapipe/Vulkan here)."""
    if "adapter" in _CACHE:
        return _CACHE["adapter"], _CACHE["reason"]
    os.environ.setdefault("XDG_RUNTIME_DIR", "/tmp/xdg")
    os.makedirs(os.environ["XDG_RUNTIME_DIR"], exist_ok=True)
    adapter, reason = None, ""
    try:
        import wgpu  # noqa: F401
    except Exception as e:  # pragma: no cover - wgpu is a core dependency
        reason = f"wgpu not importable: {e}"
    else:
        try:
            from pointflow.render.wgpu_tier.device import select_adapter
            adapter, _why = select_adapter()
        except ImportError:
            adapter = _fallback_adapter()
        except Exception as e:
            reason = f"adapter selection failed: {type(e).__name__}: {e}"
        if adapter is None and not reason:
            reason = "no wgpu adapter found (no Vulkan/Metal/D3D12/GL driver)"
    _CACHE["adapter"], _CACHE["reason"] = adapter, reason
    return adapter, reason


def _fallback_adapter() -> Optional[Any]:
    import wgpu
    adapters = list(wgpu.gpu.enumerate_adapters_sync())
    if not adapters:
        return None
    vulkan = [a for a in adapters if a.info.get("backend_type") == "Vulkan"]
    return (vulkan or adapters)[0]


def require_adapter() -> Any:
    """Return a wgpu adapter; skip (or fail under POINTFLOW_REQUIRE_GPU=1) when none."""
    adapter, reason = find_adapter()
    if adapter is None:
        _missing(reason)
    return adapter


def require_egl() -> Any:
    """Return a standalone moderngl EGL context; skip/fail like :func:`require_adapter`."""
    try:
        import moderngl
        return moderngl.create_standalone_context(backend="egl")
    except Exception as e:
        _missing(f"no EGL/OpenGL context: {type(e).__name__}: {e}")


@contextlib.contextmanager
def xvfb_display():
    """The display to use: $DISPLAY, or a private Xvfb started for the block (fails under
    POINTFLOW_REQUIRE_GPU=1 when neither exists, skips otherwise). Yields ":N"."""
    import shutil
    import subprocess

    if os.environ.get("DISPLAY"):
        yield os.environ["DISPLAY"]
        return
    xvfb = shutil.which("Xvfb")
    if xvfb is None:
        _missing("no DISPLAY and no Xvfb to start one")
    r, w = os.pipe()
    proc = subprocess.Popen([xvfb, "-displayfd", str(w), "-screen", "0", "800x600x24", "-nolisten", "tcp"],
                            pass_fds=(w,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.close(w)
    try:
        num = b""
        with os.fdopen(r, "rb") as f:
            while not num.endswith(b"\n"):
                ch = f.read(1)
                if not ch:
                    break
                num += ch
        assert num.strip(), "Xvfb did not report a display number"
        os.environ["DISPLAY"] = f":{int(num)}"
        try:
            yield f":{int(num)}"
        finally:
            os.environ.pop("DISPLAY", None)
    finally:
        import sys

        if "glfw" in sys.modules:  # drop the X connection first, or Xlib exit()s at shutdown
            sys.modules["glfw"].terminate()
        proc.terminate()
        proc.wait(timeout=10)
