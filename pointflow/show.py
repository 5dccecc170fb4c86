"""``pointflow.show``: the shortest path from a numpy cloud to a picture, no YAML.

``show(positions, **channels)`` starts a pipeline with one ``api`` source, sends the cloud
(or a sequence of clouds) and shows it with the best view this machine has, tried in the
order of :data:`VIEWS`:

1. ``notebook``: inside a Jupyter kernel with the notebook extra
   (``pip install 'pointflow[notebook]'``): a live widget (:mod:`pointflow.notebook`)
   that keeps the pipeline running until the widget is closed;
2. ``window``: a display (``DISPLAY``/``WAYLAND_DISPLAY``) and the window extra
   (``pip install pointflow[window]``): an interactive window, until it is closed;
3. ``png``: anywhere else, one frame written to a PNG whose path is printed and returned.
   Drawn in this process by the cpu tier's float64 reference (no stage is started: a one-shot
   picture of a static array needs no ring, cadence or render process, whose start costs
   seconds), with the camera and colour rules the render stage uses.
"""
from __future__ import annotations

import importlib.util
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from typing import Any, Callable, Optional, Sequence

import numpy as np

from .arrays import finite_rows
from .ingest.transports.api import SendError, check_cloud
from .notebook import in_notebook
from .render.view.protocol import BUILTIN_COLOR


@dataclass
class View:
    """One way to show clouds: ``available()`` says whether it can here, ``show(pipeline,
    total_points, path)`` shows what the pipeline holds and returns what ``show`` returns."""

    name: str
    available: Callable[[], bool]
    show: Callable[..., Any]
    #: render config this view needs (merged over show's defaults)
    render: Optional[dict] = None
    #: the view keeps the pipeline running after show returns (it stops it itself)
    keeps_running: bool = False
    #: the view draws in this process, no pipeline started: ``show(clouds, cfg, path)`` with
    #: ``clouds`` the checked ``(positions, channels)`` pairs and ``cfg`` the pipeline config
    #: show would have started
    in_process: bool = False


def _window_missing() -> Optional[str]:
    """Why no window can open here (None: one can)."""
    from .render.window import display_available

    if not display_available():
        return "no display (DISPLAY and WAYLAND_DISPLAY unset)"
    missing = [m for m in ("rendercanvas", "glfw") if importlib.util.find_spec(m) is None]
    if missing:
        return f"{', '.join(missing)} not installed (pip install 'pointflow[window]')"
    return None


def _window_available() -> bool:
    return _window_missing() is None


def _wait_drawn(p, total: int, timeout_s: float) -> None:
    """Until ingest wrote every point and the renderer drew a frame that holds them (the
    render stage draws only when something changed, so a count of frames would not do)."""
    end = time.monotonic() + timeout_s
    want = min(total, p.cfg.ring.max_points)
    while time.monotonic() < end:
        st = p.stats()
        if st.get("stages", {}).get("render", {}).get("drawn_count", 0) >= want:
            return
        p.wait(0.05)


def _show_window(p, total: int, path: Optional[str], timeout_s: float) -> Optional[str]:
    """Until the window is closed (or Ctrl-C); a window that does not open within
    ``timeout_s`` (the render stage went headless) gives the PNG instead."""
    end = time.monotonic() + timeout_s
    while not p.stats().get("stages", {}).get("render", {}).get("window"):
        if time.monotonic() > end or not p.running:
            print("pointflow.show: the window did not open; writing a PNG instead", file=sys.stderr)
            return _show_png(p, total, path, timeout_s)
        p.wait(0.05)
    _until_closed(p, "pointflow.show: window open; close it to return")
    return None


def _until_closed(p, say: str) -> None:
    """Say ``say``, then wait until the window is closed (a stop request) or Ctrl-C. In the
    main thread Ctrl-C only sets a flag the wait checks, as ``pointflow run`` does (set before
    ``say``: a Ctrl-C right after it is caught too): a KeyboardInterrupt raised inside the
    supervisor's loop can leave it half way through a step, and the stop after it hung (once,
    in CI, on a loaded machine)."""
    import signal
    import threading

    main = threading.current_thread() is threading.main_thread()
    hit: list[int] = []
    old = signal.signal(signal.SIGINT, lambda signum, _frame: hit.append(signum)) if main else None
    try:
        print(say, file=sys.stderr, flush=True)
        p.wait(None, until=lambda: bool(hit))
    except KeyboardInterrupt:  # not the main thread: Python's own handler
        pass
    finally:
        if main:
            signal.signal(signal.SIGINT, old)


def _png_path(path: Optional[str]) -> str:
    """``path`` made absolute, its suffix checked (``.png``, ``.jpg``, ``.jpeg``: a ValueError
    naming them) and its directory made, as ``Pipeline.save_frame`` does; a temporary
    ``.png`` without one."""
    from .render.imagefile import image_format

    if path is None:
        fd, path = tempfile.mkstemp(prefix="pointflow-show-", suffix=".png")
        os.close(fd)
        return path
    path = os.path.abspath(os.fspath(path))
    try:
        image_format(path)
    except ValueError as exc:
        raise ValueError(str(exc).replace("save_frame:", "show:", 1)) from None
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
    except OSError as exc:
        raise OSError(exc.errno, f"show: cannot make the directory of {path!r}: {exc.strerror}") from None
    return path


def _write(path: str, rgba: np.ndarray) -> None:
    """Write the picture; an OSError that names ``path`` (not the temporary file beside it)."""
    from .render.imagefile import write_image

    try:
        write_image(path, rgba)
    except OSError as exc:
        raise OSError(exc.errno, f"show: cannot write {path!r}: {exc.strerror or exc}") from None


def _show_png(p, total: int, path: Optional[str], timeout_s: float) -> str:
    """The running pipeline's frame once every point is drawn (the window view's fallback)."""
    out = _png_path(path)
    _wait_drawn(p, total, timeout_s)
    out = p.save_frame(out)
    print(out)
    return out


def _frame_of(clouds: list[tuple[np.ndarray, dict]], cfg):
    """The frame the render stage would get once ingest stored every point: float32 offsets
    from the ring's origin rule (the rounded median of the finite points), points too far from
    it or not finite left out (NaN: every tier skips them), channels in the ring's dtypes and
    their ranges over the values present."""
    from .render.base import FrameInput
    from .ring.layout import ChannelSpec
    from .ring.ring import MAX_OFFSET

    pos = np.concatenate([c[0] for c in clouds]).astype(np.float64, copy=False)
    n = len(pos)
    ok = finite_rows(pos)
    origin = np.round(np.median(pos[ok], axis=0)) if ok.any() else np.zeros(3)
    rel = pos - origin
    with np.errstate(invalid="ignore"):
        rel[~(np.abs(rel) < MAX_OFFSET).all(axis=1)] = np.nan
    chans, ranges = {}, {}
    for name in cfg.ring_channels():
        spec = ChannelSpec.default(name)
        shape = (n, spec.width) if spec.width > 1 else (n,)
        absent = np.full(shape, np.nan if np.dtype(spec.dtype).kind == "f" else 0, spec.dtype)
        parts = [np.asarray(c[1][name]).reshape(len(c[0]), -1) if name in c[1] else None for c in clouds]
        if any(x is None for x in parts):  # a channel no cloud has: NaN, drawn in render.color
            chans[name] = absent
            continue
        try:
            chans[name] = np.concatenate(parts).astype(spec.dtype).reshape(shape)
        except ValueError:  # another width than the ring stores: not stored, as ingest would
            chans[name] = absent
            continue
        if spec.width == 1 and np.dtype(spec.dtype).kind == "f":
            v = chans[name][np.isfinite(chans[name])]
            if v.size:
                ranges[name] = (float(v.min()), float(v.max()))
    ones = np.ones(n, np.float32)
    ranges.setdefault("importance", (1.0, 1.0))
    return FrameInput(positions=rel.astype(np.float32), importance=ones, t_ingest_ms=np.zeros(n, np.float32),
                      channels=chans, head=0, size=n, capacity=n, origin=origin, now_ms=0.0,
                      channel_ranges=ranges, dirty=None)


#: From this many points a PNG is drawn by the compiled raster when its loops are cached
#: (``pointflow warm``, or any run before): loading them costs about a second, the float64
#: reference about 1 s per million points.
COMPILED_FROM = 1_000_000


def _renderer_for(cfg, frame):
    """The cpu tier's compiled raster for a big cloud whose loops need no compiling, else its
    float64 reference (bit-exact, nothing to compile)."""
    from .render.cpu import CpuRenderer

    if frame.capacity >= COMPILED_FROM:
        from . import jitcache
        from .render import cpu_kernels

        if cpu_kernels.disabled() is None and cpu_kernels.cache_state() == jitcache.READY:
            from .render.cpu_compute import CpuComputeRenderer

            return CpuComputeRenderer(cfg.render, frame.capacity, list(frame.channels))
    return CpuRenderer(cfg.render, frame.capacity, list(frame.channels))


def _draw_png(clouds: list[tuple[np.ndarray, dict]], cfg, path: Optional[str]) -> str:
    """One frame of every point, drawn here by the cpu tier (``_renderer_for``: no device,
    nothing compiled while you wait), framed by the render stage's auto camera; written to
    ``path``."""
    from .render.view.controller import CameraController

    out = _png_path(path)  # a bad path refused before drawing
    frame = _frame_of(clouds, cfg)
    w, h = cfg.render.size
    camera = CameraController(cfg, w, h).update(frame)
    renderer = _renderer_for(cfg, frame)
    try:
        if camera is not None:  # None: not one finite point, the background alone
            renderer.render(frame, camera)
        _write(out, renderer.read_image())
    finally:
        renderer.close()
    print(out)
    return out


def _notebook_available() -> bool:
    from .notebook import available

    return in_notebook() and available()


def _show_notebook(p, total: int, path: Optional[str], timeout_s: float) -> None:
    """The live widget, displayed; it owns the pipeline (closing the widget stops it)."""
    from IPython.display import display

    from .notebook import LiveView

    _wait_drawn(p, total, timeout_s)
    w, h = p.cfg.render.size
    display(LiveView(p, width=w, height=h, owns_pipeline=True))


#: Tried in order; the first available one shows. A notebook view registers itself here
#: with :func:`register_view` (first in the list).
VIEWS: list[View] = [
    View("notebook", _notebook_available, _show_notebook, keeps_running=True),
    View("window", _window_available, _show_window, render={"window": True}),
    View("png", lambda: True, _draw_png, in_process=True),
]


def register_view(view: View) -> None:
    """Put ``view`` first (a notebook view: ``View("notebook", in_notebook, its_show)``)."""
    VIEWS[:] = [view] + [v for v in VIEWS if v.name != view.name]


def _clouds(positions: Any, channels: dict) -> list[tuple[np.ndarray, dict]]:
    """One cloud, or a sequence of clouds (a list/tuple of (n, 3) arrays, each channel then
    a list of the same length), checked; :class:`SendError` names the argument."""
    if isinstance(positions, (str, bytes, os.PathLike)):
        raise SendError("bad_positions", f"positions: expected an (n, 3) float array, got the path {os.fspath(positions)!r}; "
                                         "show draws arrays: read the file first (e.g. laspy), or run "
                                         "`pointflow run` on a config whose source reads it (transport: file)")
    seq = isinstance(positions, (list, tuple)) and len(positions) > 0 and \
        all(isinstance(x, np.ndarray) and x.ndim == 2 for x in positions)
    if not seq:
        pos, chans = check_cloud(positions, channels, None, None)
        return [(pos, chans)]
    out = []
    for name, v in channels.items():
        if not isinstance(v, (list, tuple)) or len(v) != len(positions):
            raise SendError("length_mismatch", f"channel {name!r}: with a sequence of {len(positions)} clouds, expected a "
                                               f"list of {len(positions)} arrays, got {type(v).__name__}"
                                               + (f" of {len(v)}" if isinstance(v, (list, tuple)) else ""))
    for i, pos in enumerate(positions):
        try:
            out.append(check_cloud(pos, {k: v[i] for k, v in channels.items()}, None, None))
        except SendError as exc:
            raise SendError(exc.reason, f"cloud {i}: {exc}") from None
    return out


def _say_unseen(clouds: list[tuple[np.ndarray, dict]], total: int) -> None:
    """Say on stderr when points will not be seen: none given, or some (or all) with a
    NaN or infinite coordinate (every tier skips those)."""
    if total == 0:
        print("pointflow.show: no points given: the picture is the background alone", file=sys.stderr)
        return
    bad = total - sum(int(np.count_nonzero(finite_rows(c[0]))) for c in clouds)
    if bad:
        what = "all" if bad == total else f"{bad:,} of {total:,}"
        print(f"pointflow.show: {what} points have a NaN or infinite coordinate and are not drawn",
              file=sys.stderr)


def show_config(total: int, names: list[str], color_by: str, size: Sequence[int], render: Optional[dict] = None):
    """The pipeline config of a show: one ``api`` source named ``show``, the ring sized to
    the points and keeping the channels given, ``render`` merged over show's render block."""
    from .config import load_config

    block = {"size": list(size), "color_by": color_by, "output": {"dir": None}, "camera": {"mode": "auto"},
             **(render or {})}
    return load_config({"name": "show", "sources": [{"transport": "api", "name": "show"}],
                        "ring": {"max_points": max(total, 1), "extra_channels": [n for n in names if n != color_by]},
                        "render": block, "tracing": {"enabled": False}, "cadence": {"target_hz": 10}})


def show(positions: Any, *, path: Optional[str] = None, color_by: Optional[str] = None,
         size: Sequence[int] = (1280, 720), view: Optional[str] = None, timeout_s: float = 120.0,
         **channels: Any) -> Optional[str]:
    """Show one cloud (``(n, 3)`` float32/float64) or a sequence of clouds, with channels
    (``intensity=...``), in the best view available. Colours by ``color_by`` (default: the
    first channel given, else height). Returns the PNG's path (also printed) when it wrote
    one, None after a window was closed. ``view`` forces one of :data:`VIEWS` by name."""
    clouds = _clouds(positions, channels)
    total = sum(len(c[0]) for c in clouds)
    _say_unseen(clouds, total)
    if path is not None:
        path = _png_path(path)  # a bad suffix or directory refused before anything starts
    names = list(clouds[0][1])
    if color_by is None:
        color_by = names[0] if names else "z"
    elif color_by not in names and color_by not in BUILTIN_COLOR:
        raise SendError("unknown_channel", f"color_by: {color_by!r} is not among the channels given "
                                           f"({', '.join(names) or 'none'}) nor z, height, ingest_time")
    if view is not None:
        chosen = next((v for v in VIEWS if v.name == view), None)
        if chosen is None:
            raise ValueError(f"view: expected one of {', '.join(v.name for v in VIEWS)}, got {view!r}")
        why = _window_missing() if chosen.name == "window" else None
        if why is not None:  # say so now: the render stage would go headless and show wait timeout_s
            print(f"pointflow.show: no window here: {why}; writing a PNG instead", file=sys.stderr)
            chosen = next(v for v in VIEWS if v.name == "png")
    else:
        chosen = next(v for v in VIEWS if v.available())
    cfg = show_config(total, names, color_by, size, chosen.render)
    if chosen.in_process:
        return chosen.show(clouds, cfg, path)
    from .runtime.pipeline import Pipeline

    p = Pipeline(cfg, out_dir="")
    p.start()
    kept = False
    try:
        for pos, chans in clouds:
            p.send(pos, source="show", **chans)
        out = chosen.show(p, total, path, timeout_s)
        kept = chosen.keeps_running
        return out
    finally:
        if not kept:
            p.stop()


__all__ = ["show", "register_view", "View", "VIEWS", "in_notebook"]
