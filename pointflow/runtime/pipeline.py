"""The Python API: build a pipeline from YAML or a dict, run it, read its numbers."""
from __future__ import annotations

import atexit
import json
import logging
import os
import sys
import time
from pathlib import Path
from typing import Any, Callable, Optional, Union

from ..config import PipelineConfig, load_config
from ..typed import ConfigError
from .supervisor import PipelineFailed, Supervisor, planned_stages

log = logging.getLogger("pointflow")

#: What ``Pipeline.show()`` says outside a notebook (it has no widget to show there).
NOT_IN_NOTEBOOK = ("Pipeline.show(): not inside a Jupyter notebook, so no widget was shown; here, see the "
                   "pipeline in a window (render.window: true), in a browser (serve:, or `pointflow run --serve`; "
                   "docs/views.md) or in a file (p.save_frame('frame.png'))")

#: "argument not given" (None is a value for some, e.g. ``style(color_by=None)``).
_UNSET: Any = type("_Unset", (), {"__repr__": lambda self: "<unset>"})()


def _plain(args: dict) -> dict:
    """numpy arrays and scalars as JSON-ready lists and floats."""
    import numpy as np

    return {k: (np.asarray(v).tolist() if isinstance(v, (np.ndarray, np.generic)) else v) for k, v in args.items()}


def with_api_source(data: dict) -> dict:
    """``data`` with one ``api`` source named ``api`` when it names none (no ``source``,
    ``sources`` or ``router``): a pipeline built in Python with no source is fed by
    :meth:`Pipeline.send`. A YAML file still needs its source (``pointflow run`` has no caller
    to send)."""
    if not isinstance(data, dict) or any(k in data for k in ("source", "sources", "router")):
        return data
    return {**data, "sources": [{"transport": "api", "name": "api"}]}


class RunStats(dict):
    """A run's final stats (``Pipeline.stop``, ``run``): a plain dict of every counter, with
    a one-line repr, so a notebook cell or a REPL ending in ``p.stop()`` prints a line."""

    def __repr__(self) -> str:
        if not self:
            return "Stopped()"
        acc = self.get("accounting") or {}
        parts = [f"frames={self.get('frames', 0)}", f"elapsed_s={self.get('elapsed_s', 0.0):g}"]
        if "ring_written" in acc:
            parts.append(f"ring_written={acc['ring_written']}")
        if self.get("failure"):
            parts.append(f"failure={str(self['failure'])[:80]!r}")
        return f"Stopped({', '.join(parts)})"

    def _repr_pretty_(self, printer, cycle: bool) -> None:  # IPython: the same one line
        printer.text(repr(self))


def _check_duration(d) -> None:
    """``duration_s`` as ``pointflow run --duration`` takes it: None or a number >= 0."""
    import math

    if d is None:
        return
    if isinstance(d, bool) or not isinstance(d, (int, float)) or not math.isfinite(d) or d < 0:
        raise ValueError(f"duration_s: expected a number of seconds >= 0 or None, got {d!r}")


def prepare_out_dir(path: str) -> str:
    """Create the output directory up front, so a bad one is a :class:`ConfigError` naming
    it (``pointflow run --out`` and ``Pipeline.start``), not an OSError from a stage."""
    if os.path.exists(path) and not os.path.isdir(path):
        raise ConfigError("", f"output directory {path}: exists and is not a directory")
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as exc:
        raise ConfigError("", f"cannot create output directory {path}: {exc.strerror or exc}") from None
    return path


class Pipeline:
    """A running (or runnable) pointflow pipeline.

    >>> with Pipeline.from_yaml("configs/demo.yaml", out_dir="out") as p:
    ...     p.wait(5)
    ...     print(p.stats()["frames"])
    """

    def __init__(self, cfg: Optional[PipelineConfig] = None, out_dir: Optional[str] = None, role: str = "pipeline"):
        #: No config: every default, with the ``api`` source ``send`` feeds (:func:`with_api_source`).
        self.cfg = cfg if cfg is not None else load_config(with_api_source({}))
        #: "send": run only the sources and publish them on ``cfg.send`` (``pointflow send``).
        self.role = role
        self.out_dir = out_dir if out_dir is not None else self.cfg.render.output.dir
        if self.out_dir:
            self.out_dir = str(Path(self.out_dir).resolve())
        self._sup: Optional[Supervisor] = None
        self._final: Optional[dict] = None

    @classmethod
    def from_yaml(cls, path: Union[str, os.PathLike], out_dir: Optional[str] = None) -> "Pipeline":
        return cls(load_config(path), out_dir=out_dir)

    @classmethod
    def from_dict(cls, data: dict, out_dir: Optional[str] = None, base_dir: Optional[str] = None) -> "Pipeline":
        """A pipeline from a config dict; one that names no source gets the ``api`` source
        :meth:`send` feeds (:func:`with_api_source`)."""
        return cls(load_config(with_api_source(data), base_dir=base_dir), out_dir=out_dir)

    # ------------------------------------------------------------------ lifecycle
    def start(self, wait: bool = True) -> "Pipeline":
        """Start every stage; return once each has reported in (``wait``, the default: then
        ``wait(5)`` is five seconds of a running pipeline), or at once after spawning them
        (``wait=False``: :attr:`starting` says when they are all in; ``send`` works already,
        its clouds wait in ingest's socket)."""
        if self._sup is not None and self._sup.started:
            raise RuntimeError("pipeline already running")
        if self.out_dir:
            prepare_out_dir(self.out_dir)  # a ConfigError naming it, before anything starts
        self._final = None
        self._sup = Supervisor(self.cfg, out_dir=self.out_dir, role=self.role)
        atexit.register(self.stop)
        try:
            self._sup.start(wait)
        except BaseException:
            sup, self._sup = self._sup, None  # nothing left for stop() or the exit hook to do
            atexit.unregister(self.stop)
            sup.stop()
            sup._release()
            raise
        return self

    @property
    def starting(self) -> bool:
        """Started, and some stage has not reported in yet (within ``supervisor.startup_timeout_ms``)."""
        return self._sup is not None and self._sup.starting()

    def stages(self) -> list[str]:
        """The stages this pipeline runs (or would), in start order."""
        if self._sup is not None:
            return list(self._sup.stages)
        return planned_stages(self.cfg, self.role)

    @property
    def running(self) -> bool:
        return self._sup is not None and self._sup.alive()

    def poll(self, timeout_s: float = 0.05) -> None:
        """Service the supervisor (heartbeats, restarts); :meth:`wait` calls it for you.

        Raises :class:`PipelineFailed` when a stage failed past its restart limit."""
        if self._sup is None:
            return
        self._sup.poll(timeout_s)
        if self._sup.failure:
            raise PipelineFailed(self._sup.failure, self._sup.failure_cause)

    @property
    def stop_requested(self) -> Optional[str]:
        """Why a stage asked to end the run (the window was closed), or None."""
        return self._sup.stop_requested if self._sup is not None else None

    def wait(self, duration_s: Optional[float] = None, until: Optional[Callable[[], bool]] = None) -> bool:
        """Run the supervisor loop for ``duration_s`` seconds (None = until ``until()`` is
        true, or forever); returns early when a stage asks to stop the run. True when
        ``until()`` came true; False when the time ran out or the run was asked to stop (so
        ``if not p.wait(10, until=...)`` tells a timeout). A ValueError for a duration that
        is not a number >= 0; a RuntimeError before the first :meth:`start`, as :meth:`stats`."""
        _check_duration(duration_s)
        if self._sup is None and self._final is None:  # never started (after a stop: False at once)
            raise RuntimeError("pipeline is not running: call start() first (or use `with Pipeline... as p:`)")
        end = None if duration_s is None else time.monotonic() + duration_s
        while (end is None or time.monotonic() < end) and not self.stop_requested:
            self.poll(0.05 if end is None else max(0.0, min(0.05, end - time.monotonic())))
            if until is not None and until():
                return True
        return False

    def stop(self) -> "RunStats":
        """Stop every stage, unlink shared memory, write ``stats.json``; idempotent. Returns
        the final stats: a dict whose repr is one line (a notebook cell ending in
        ``p.stop()`` shows ``Stopped(frames=..., elapsed_s=...)``, not the whole dict)."""
        if self._sup is None:
            return self._final if self._final is not None else RunStats()
        sup, self._sup = self._sup, None
        try:
            atexit.unregister(self.stop)
        except Exception:  # noqa: BLE001
            pass
        sup.stop()
        self._final = RunStats(sup.stats())
        self._final["config"] = self.cfg.to_dict()
        self._collector = sup.collector
        if self.out_dir:
            os.makedirs(self.out_dir, exist_ok=True)
            with open(os.path.join(self.out_dir, "stats.json"), "w") as f:
                json.dump(self._final, f, indent=2, default=str)
        return self._final

    def run(self, duration_s: Optional[float] = None) -> dict:
        """Start, run for ``duration_s`` (None = until interrupted), stop; returns stats."""
        _check_duration(duration_s)
        self.start()
        try:
            self.wait(duration_s)
        finally:
            stats = self.stop()
        return stats

    def pick(self, x: float, y: float, pixel_ratio: float = 1.0, timeout_s: float = 10.0) -> Optional[dict]:
        """The point under window pixel (x, y) in the last frame, resolved through the ring:
        ``{"slot", "position" (float64 world), "channels", "t_ingest_ms", "generation"}``,
        or None when nothing is within ``render.pick_radius``."""
        rep = self._request({"cmd": "pick", "x": x, "y": y, "pixel_ratio": pixel_ratio}, timeout_s)
        return rep.get("point")

    def save_frame(self, path: str, timeout_s: float = 10.0) -> str:
        """Write the current frame at ``path`` (on request, besides every N frames): PNG for
        ``.png``, JPEG for ``.jpg``/``.jpeg``; any other suffix is a ValueError naming them."""
        from ..render.imagefile import image_format

        image_format(path)  # refused here, before the render stage is asked
        d = os.path.dirname(os.path.abspath(path))
        while d and not os.path.exists(d) and os.path.dirname(d) != d:
            d = os.path.dirname(d)  # the nearest folder that exists (the render stage makes the rest)
        if d and os.path.exists(d) and not os.path.isdir(d):
            raise ValueError(f"path: {d} is a file, not a folder: cannot write {path}")
        rep = self._request({"cmd": "save", "path": os.path.abspath(path)}, timeout_s)
        return rep["path"]

    # ------------------------------------------------------------------ sending (docs/api.md)
    def send(self, positions, *, source: str = "api", frame: Optional[str] = None,
             stamp_ns: Optional[int] = None, **channels) -> int:
        """Send one cloud from this process: ``positions`` float32/float64 ``(n, 3)``, each
        channel a numpy array of length n (``intensity=...``), ``frame`` its coordinate frame,
        ``stamp_ns`` its capture time. ``source`` names an ``api`` source: declared in the
        config, or added now with backpressure ``block``. Returns n once the cloud is handed
        to the pipeline (the arrays may be reused at once); :class:`ValueError` naming the
        argument on bad input, the pipeline going on. Safe from several threads."""
        return self._api(source).send(positions, frame, stamp_ns, **channels)

    def send_transforms(self, transforms, *, source: str = "api") -> int:
        """Send transforms (dicts with ``parent``, ``child``, ``stamp_ns``, ``translation``,
        ``rotation`` (x, y, z, w), ``static``; docs/wire-format.md), in order with the clouds
        of ``source``. Returns how many."""
        return self._api(source).send_transforms(transforms)

    def _api(self, name: str):
        sup = self._sup
        if sup is None or not sup.started:
            raise RuntimeError("pipeline is not running: call start() first (or use `with Pipeline... as p:`)")
        st = sup.stages.get(name)
        if st is not None and st.local is not None:
            return st.local
        if not isinstance(name, str) or not name:
            raise ValueError(f"source: expected a source name (a non-empty str), got {name!r}")
        return sup.add_local_source(name)

    # ------------------------------------------------------------------ steer the view (docs/api.md)
    def camera(self, *, eye=None, target=None, up=None, fov_deg: Optional[float] = None, wait: bool = True) -> dict:
        """Set the camera (world coordinates; any subset). The view stays there until
        :meth:`fit`. Returns the view state (:meth:`view_state`)."""
        args = {k: v for k, v in (("eye", eye), ("target", target), ("up", up), ("fov_deg", fov_deg)) if v is not None}
        return self.control({"cmd": "camera", **_plain(args)}, wait=wait)

    def orbit(self, azimuth_deg: float = 0.0, elevation_deg: float = 0.0, wait: bool = True) -> dict:
        """Turn the eye about the target (degrees; azimuth counter-clockwise about up)."""
        return self.control({"cmd": "orbit", "azimuth_deg": azimuth_deg, "elevation_deg": elevation_deg}, wait=wait)

    def pan(self, right: float = 0.0, up: float = 0.0, wait: bool = True) -> dict:
        """Move eye and target sideways by fractions of the view height."""
        return self.control({"cmd": "pan", "right": right, "up": up}, wait=wait)

    def zoom(self, factor: float, wait: bool = True) -> dict:
        """Move towards the target: 2 = twice as close, 0.5 = twice as far."""
        return self.control({"cmd": "zoom", "factor": factor}, wait=wait)

    def fit(self, wait: bool = True) -> dict:
        """Frame the data again (and follow it as it grows)."""
        return self.control({"cmd": "fit"}, wait=wait)

    def follow(self, frame: Optional[str], wait: bool = True) -> dict:
        """Keep the camera's offset from ``frame``'s origin as it moves (a frame of the
        transforms, looked up in ``frames.fixed``); None stops following."""
        return self.control({"cmd": "follow", "frame": frame}, wait=wait)

    def style(self, *, color_by: Any = _UNSET, colormap: Any = _UNSET, color_range: Any = _UNSET,
              point_size: Any = _UNSET, point_shape: Any = _UNSET, edl: Any = _UNSET, edl_strength: Any = _UNSET,
              time_window_ms: Any = _UNSET, wait: bool = True) -> dict:
        """Change how points are drawn (only the arguments given). ``color_by``: a ring
        channel, ``z``, ``ingest_time`` or None; ``color_range``: ``'auto'`` or ``[lo, hi]``."""
        args = {k: v for k, v in locals().items() if k not in ("self", "wait") and v is not _UNSET}
        return self.control({"cmd": "style", **_plain(args)}, wait=wait)

    def visible(self, source: str, on: bool = True, wait: bool = True) -> dict:
        """Show (``on=True``) or hide a source's points (pipelines with two or more sources)."""
        return self.control({"cmd": "visible", "source": source, "on": on}, wait=wait)

    def view_state(self) -> dict:
        """The view now: ``camera``, ``style``, ``version``, ``drawn_version`` (the version
        the last frame showed), ``camera_drawn`` and ``view_block`` (for a YAML ``view:``)."""
        return self.control({"cmd": "view_state"}, wait=False)

    def save_view(self, path: Union[str, os.PathLike]) -> str:
        """Write the view as a YAML ``view:`` block; put it in a pipeline YAML to start there."""
        import yaml

        block = self.view_state()["view_block"]
        with open(path, "w") as f:
            yaml.safe_dump({"view": block}, f, sort_keys=False)
        return str(path)

    def control(self, msg: dict, wait: bool = True, timeout_s: float = 10.0) -> dict:
        """Send one view control message (render/view/protocol.py); with ``wait`` return once a
        frame shows it (or ``timeout_s`` passed: nothing to draw yet). A refused message
        raises :class:`~pointflow.render.view.protocol.ControlError` naming the argument."""
        from ..render.view.protocol import ControlError

        if self._sup is None:
            raise RuntimeError("pipeline is not running")
        rep = self._sup.request(msg, timeout_s)
        if "error" in rep:
            if "key" in rep:
                raise ControlError(rep["key"], rep["message"])
            raise RuntimeError(f"render stage: {rep['error']}")
        end = time.monotonic() + timeout_s
        while wait and rep["drawn_version"] < rep["version"] and time.monotonic() < end:
            time.sleep(0.005)
            rep = self._sup.request({"cmd": "view_state"}, timeout_s)
        return rep

    # ------------------------------------------------------------------ steer the replay (docs/api.md)
    def playback(self, source: Optional[str] = None, *, paused: Optional[bool] = None, seek_s: Optional[float] = None,
                 seek_fraction: Optional[float] = None, step: int = 0, rate: Optional[float] = None,
                 loop: Optional[bool] = None, hold: Optional[bool] = None, timeout_s: float = 5.0) -> dict[str, dict]:
        """Steer the replaying sources (``file``, ``rosbag``): all of them, or ``source`` by
        name. With no argument it only reads their state. ``hold``: at the end (no loop) wait
        for a seek instead of ending the source. Returns ``{source name: state}``
        (``paused``, ``rate``, ``loop``, ``position_s``, ``index`` of the last message sent,
        ``next_s`` of the one waiting to go, ``duration_s``, ``seeks``, ``steps``...). A seek
        returns once it has landed: the sought message went out (``position_s``; paused, it
        goes once and the replay stays paused); past the last message, the replay is at its end.
        A step returns once its messages went out. Not landed within ``timeout_s``: raises
        :class:`TimeoutError`. A refused argument raises
        :class:`~pointflow.ingest.playback.PlaybackError` naming it."""
        from ..ingest.playback import PlaybackError, playback_endpoint, request
        from ..ingest.transports import resolve_transport

        if self._sup is None:
            raise RuntimeError("pipeline is not running")
        msg: dict[str, Any] = {"cmd": "playback"}
        for k, v in (("paused", paused), ("seek_s", seek_s), ("seek_fraction", seek_fraction), ("rate", rate),
                     ("loop", loop), ("hold", hold)):
            if v is not None:
                msg[k] = v.item() if hasattr(v, "item") else v
        if step:
            msg["step"] = step
        replays = [(i, s) for i, s in enumerate(self.cfg.sources)
                   if not s.external and getattr(resolve_transport(s.transport), "seekable", False)]
        if source is not None:
            replays = [(i, s) for i, s in replays if s.name == source]
            if not replays:
                names = [s.name for i, s in enumerate(self.cfg.sources)
                         if getattr(resolve_transport(s.transport), "seekable", False)]
                raise PlaybackError("source", f"no replaying source named {source!r}; replaying sources: "
                                    f"{', '.join(names) or 'none (only file and rosbag sources replay)'}")
        if not replays:
            raise PlaybackError("source", "this pipeline has no replaying source (file or rosbag)")
        out = {}
        for i, s in replays:
            try:
                rep = request(self._sup._zctx, playback_endpoint(self._sup.endpoints.playback, i), msg, timeout_s)
            except TimeoutError:
                raise RuntimeError(f"source {s.name!r} did not answer within {timeout_s} s: its replay has ended "
                                   "(hold=True keeps it waiting for a seek) or it is restarting") from None
            if "error" in rep:
                raise PlaybackError(rep.get("key", "cmd"), rep.get("message", rep["error"]))
            out[s.name] = rep["state"]
        if seek_s is not None or seek_fraction is not None or step:
            end = time.monotonic() + timeout_s
            what = (f"the seek to {seek_s:g} s" if seek_s is not None else
                    "the seek" if seek_fraction is not None else f"the step of {step}")
            for i, s in replays:
                out[s.name] = self._landed(i, s.name, out[s.name], end, what, timeout_s)
        return out

    def _landed(self, index: int, name: str, st: dict, end: float, what: str, timeout_s: float) -> dict:
        """Poll a source's playback state until its seeks have landed (``seeks_landed``) and
        its steps went out (``steps_pending``; or it is at its end)."""
        from ..ingest.playback import playback_endpoint, request

        ep = playback_endpoint(self._sup.endpoints.playback, index)
        while st["seeks_landed"] < st["seeks"] or (st["steps_pending"] and not st["at_end"]):
            if time.monotonic() > end:
                raise TimeoutError(f"source {name!r}: {what} has not landed within {timeout_s:g} s "
                                   "(the source is busy or restarting); p.playback() reads its state")
            time.sleep(0.01)
            try:
                st = request(self._sup._zctx, ep, {"cmd": "playback"}, max(0.1, end - time.monotonic()))["state"]
            except TimeoutError:
                raise RuntimeError(f"source {name!r} did not answer after the seek: its replay has ended "
                                   "(hold=True keeps it waiting for a seek) or it is restarting") from None
        return st

    def _request(self, msg: dict, timeout_s: float) -> dict:
        if self._sup is None:
            raise RuntimeError("pipeline is not running")
        rep = self._sup.request(msg, timeout_s)
        if "error" in rep:
            raise RuntimeError(f"render stage: {rep['error']}")
        return rep

    def stats(self) -> dict[str, Any]:
        """Live numbers while running, the final ones after :meth:`stop`; before the first
        :meth:`start` there are none (RuntimeError, as for :meth:`send`)."""
        if self._sup is not None:
            return self._sup.stats()
        if self._final is None:
            raise RuntimeError("pipeline has not run: call start() first (or use `with Pipeline... as p:`); "
                               "stats() are live while it runs and final after stop()")
        return self._final

    def show(self, width: int = 640, height: int = 400):
        """A live view of this (started) pipeline in a notebook: an anywidget with its own
        camera (``pip install 'pointflow[notebook]'``; docs/views.md). Show it as a cell's value.
        Outside a notebook there is nothing to show it in: it says so on stderr, with the views
        that work there, and returns None."""
        from ..notebook import LiveView, available, in_notebook

        if not in_notebook():
            print(NOT_IN_NOTEBOOK, file=sys.stderr, flush=True)
            return None
        if not available():
            raise RuntimeError("Pipeline.show needs the notebook extra: pip install 'pointflow[notebook]'")
        return LiveView(self, width=width, height=height)

    @property
    def supervisor(self) -> Optional[Supervisor]:
        return self._sup

    @property
    def collector(self):
        """The span collector (profiling), also after stop."""
        if self._sup is not None:
            return self._sup.collector
        return getattr(self, "_collector", None)

    def __enter__(self) -> "Pipeline":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


__all__ = ["Pipeline", "PipelineFailed", "RunStats"]
