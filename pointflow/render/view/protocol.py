"""The view protocol, written once: messages, state, validation, limits, credit, typed errors.

Every view (the window, Python's ``Pipeline.view``, the page of pointflow/serve, the
notebook widget) speaks this vocabulary; render, serve and the notebook import it from
here and keep no copy (tests/view/test_protocol_once.py guards that).

A view is a :class:`ViewState`: a camera (``auto`` = framed on the data, following it as it
grows; ``fixed`` = an eye/target/up/fov the user set or turned) and a style (colouring,
point size and shape, eye-dome lighting, time window). A control message is a small JSON
object ``{"cmd": NAME, ...}``; :func:`apply` checks it and returns the new state, or raises
:class:`ControlError` naming the argument and what was expected. The module holds no
sockets and no renderer, so a server with several views keeps one ``ViewState`` per view
and feeds each its own messages; the render stage (``render/process.py``) is one such user.

Messages (docs/api.md "Steer the view", docs/architecture.md):

=================  ===========================================================================
``camera``         ``eye``, ``target``, ``up`` ([x, y, z] world), ``fov_deg`` (0..180): any subset
``orbit``          ``azimuth_deg``, ``elevation_deg``: turn the eye about the target
``pan``            ``right``, ``up``: move eye and target by these fractions of the view height
``zoom``           ``factor`` > 0: 2 = twice as close to the target
``fit``            back to ``auto``: frame the data (and follow it)
``follow``         ``frame``: keep the camera's offset from that frame's origin as it moves
                   (a frame of ``frames``, looked up in ``frames.fixed``); null: stop
``style``          ``color_by``, ``colormap``, ``color_range`` ('auto' or [lo, hi]), ``point_size``,
                   ``point_shape``, ``edl`` (bool), ``edl_strength``, ``time_window_ms``
``visible``        ``source`` (a source name), ``on`` (bool): show or hide that source's points
``view_state``     no change; the reply is the state
=================  ===========================================================================

Every reply is the state after the message (:meth:`ViewState.to_dict`) with ``version``
(raised by every change); the render stage adds ``drawn_version``, the version of the last
frame drawn, so a caller can wait for the frame that shows its change.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np

from ...errors import KeyedError
from .. import colormap
from ..camera import Camera, OrbitController
from ..config import MAX_SCREEN_POINT_PX

__all__ = ["ControlError", "ViewState", "CameraState", "StyleState", "apply", "COMMANDS", "BUILTIN_COLOR",
           "load_view_block", "view_block", "style_render_config", "MAX_POINT_SIZE_PX",
           "MAX_CAMERA_COORD", "number", "printable", "MAX_CREDIT", "MAX_VIEWS", "SIZE_RANGE", "MAX_VIEW_PX",
           "MAX_MESSAGE_BYTES", "COLORMAPS", "color_by_options", "gone_reply", "is_gone", "point_to_dict",
           "check_size", "check_keys"]

#: Colourings that need no ring channel.
BUILTIN_COLOR = ("z", "height", "ingest_time", "none")
#: The colourings a client offers besides the ring's channels ("height" is z under another name).
_OFFERED_BUILTIN = ("z", "ingest_time", "none")
#: The colormaps a style may name.
COLORMAPS = tuple(colormap.NAMES)
#: The style fields and the type each one takes.
_STYLE_KEYS = ("color_by", "colormap", "color_range", "point_size", "point_shape", "edl", "edl_strength",
               "time_window_ms")
_CAMERA_KEYS = ("eye", "target", "up", "fov_deg")
#: The control messages every view takes (the table above).
COMMANDS = ("camera", "orbit", "pan", "zoom", "fit", "follow", "style", "visible", "view_state")
#: Frames a client may have in flight between credit and display (jupyter_rfb's rule: two).
MAX_CREDIT = 2
#: Views one render stage serves at once (an ``open`` beyond is refused with an error).
MAX_VIEWS = 64
#: A view's width and height in pixels: the render stage draws no larger, a client asks no larger.
SIZE_RANGE = (16, 4096)
MAX_VIEW_PX = SIZE_RANGE[1]
#: A message from a view server larger than this disconnects it (ZMQ_MAXMSGSIZE).
MAX_MESSAGE_BYTES = 64 * 1024
#: The ring channel that says which configured source a point came from (pipelines with
#: two or more sources; the source stage adds it to every chunk).
SOURCE_CHANNEL = "source_index"
#: The largest screen-space point a style may ask for, in pixels (render/config.py). A
#: point's raster cost grows with its area: on the compiled cpu raster at 320x240 a 4096 px
#: point covers the whole picture, and one style message made every frame take 17-18 s.
MAX_POINT_SIZE_PX = MAX_SCREEN_POINT_PX
#: A camera's eye and target stay within this distance of the world origin (metres): far
#: beyond any data, and far from where float64 view matrices lose every digit or overflow
#: (a pan by 1e308 would make a NaN camera).
MAX_CAMERA_COORD = 1e12
_CTRL = {c: f"\\x{c:02x}" for c in list(range(0x20)) + [0x7f]}


def printable(text: Any, limit: int = 200) -> str:
    """``text`` with control characters escaped (newlines, ANSI escapes: a client's string
    cannot forge a log line or steer the operator's terminal) and cut to ``limit``."""
    s = str(text)
    s = s if len(s) <= limit else s[:limit] + "…"
    return s.translate(_CTRL)


def color_by_options(channels) -> list[str]:
    """What a client offers to colour by: the ring's channels (not the source marker) and the
    built-in colourings."""
    return [c for c in channels if c != SOURCE_CHANNEL] + list(_OFFERED_BUILTIN)


def gone_reply(view: Optional[str], req: Any) -> dict:
    """The render stage's answer to a message for a view it does not hold (it restarted, or
    the view was closed): typed by ``gone``, so a client opens the view again without
    reading the text."""
    return {"type": "error", "view": view, "req": req, "key": "view", "gone": True,
            "error": "view: unknown view (the render stage does not hold it: open it again)"}


def is_gone(head: dict) -> bool:
    """True for :func:`gone_reply`'s message."""
    return head.get("type") == "error" and head.get("gone") is True


def point_to_dict(rec) -> Optional[dict]:
    """A ring point (``PointRing.get_point``) as a pick reply's ``point``."""
    if rec is None:
        return None
    chans = {k: (np.asarray(v).tolist()) for k, v in rec.channels.items()}
    return {"slot": int(rec.slot), "position": [float(v) for v in rec.position], "channels": chans,
            "t_ingest_ms": float(rec.t_ingest_ms), "generation": int(rec.generation),
            "importance": float(getattr(rec, "importance", 1.0))}


class ControlError(KeyedError):
    """A control message (or ``view:`` block) that cannot be applied; ``key`` names the argument."""

    def __init__(self, key: str, message: str):
        # both may hold what a client sent: logged and replied safely
        super().__init__(printable(key, 80), printable(message, 400))

    @staticmethod
    def _text(key: str, message: str) -> str:
        return f"{key}: {message}"


@dataclass
class CameraState:
    #: ``auto``: framed on the data by the render stage; ``fixed``: the fields below.
    mode: str = "auto"
    eye: Optional[list[float]] = None
    target: Optional[list[float]] = None
    up: list[float] = field(default_factory=lambda: [0.0, 0.0, 1.0])
    fov_deg: float = 60.0
    #: A frame whose origin the camera follows (eye and target keep their offset from it).
    follow: Optional[str] = None
    #: Where that origin was when following began: eye and target are drawn shifted by
    #: (origin now - anchor), so orbit, zoom and pan still work while following.
    follow_anchor: Optional[list[float]] = None


@dataclass
class StyleState:
    color_by: Optional[str] = "intensity"
    colormap: str = "turbo"
    color_range: Any = "auto"
    point_size: float = 2.0
    point_shape: str = "square"
    edl: bool = False
    edl_strength: float = 1.0
    time_window_ms: float = 0.0


@dataclass
class ViewState:
    camera: CameraState = field(default_factory=CameraState)
    style: StyleState = field(default_factory=StyleState)
    #: Names of the sources whose points are not drawn.
    hidden_sources: list[str] = field(default_factory=list)
    #: Raised by every change (a reply says which version a frame must reach to show it).
    version: int = 0

    @classmethod
    def from_render_config(cls, r) -> "ViewState":
        """The state a :class:`~pointflow.config.RenderConfig` starts from."""
        c = r.camera
        cam = CameraState(mode="fixed" if c.mode == "fixed" else "auto",
                          eye=list(map(float, c.position)) if c.mode == "fixed" else None,
                          target=list(map(float, c.target)) if c.mode == "fixed" else None,
                          up=list(map(float, c.up)), fov_deg=float(c.fov_deg))
        st = StyleState(color_by=r.color_by, colormap=r.colormap,
                        color_range=r.color_range if r.color_range == "auto" else list(map(float, r.color_range)),
                        point_size=float(r.point_size), point_shape=r.point_shape, edl=bool(r.edl.enabled),
                        edl_strength=float(r.edl.strength), time_window_ms=float(r.time_window_ms))
        return cls(camera=cam, style=st)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def copy(self) -> "ViewState":
        return ViewState(camera=dataclasses.replace(self.camera, up=list(self.camera.up),
                                                    follow_anchor=None if self.camera.follow_anchor is None
                                                    else list(self.camera.follow_anchor)),
                         style=dataclasses.replace(self.style), hidden_sources=list(self.hidden_sources),
                         version=self.version)


# --------------------------------------------------------------------------- checks
def _vec3(v: Any, key: str) -> list[float]:
    if not isinstance(v, (list, tuple, np.ndarray)) or len(v) != 3:
        raise ControlError(key, f"expected [x, y, z] (3 numbers), got {_short(v)}")
    return [number(x, key, -MAX_CAMERA_COORD, MAX_CAMERA_COORD) for x in v]


def _short(v: Any) -> str:
    """A client's value in an error message: its repr, cut (a 400-digit number or a deep
    list says what it was without filling the log)."""
    try:
        r = repr(v)
    except (ValueError, RecursionError):  # an int past Python's digit limit, a cycle
        r = f"<{type(v).__name__}>"
    return r if len(r) <= 60 else r[:57] + "..."


def number(v: Any, key: str, lo: float = -math.inf, hi: float = math.inf, lo_open: bool = False,
           hi_open: bool = False) -> float:
    """``v`` as a finite float in the range, else :class:`ControlError` naming ``key`` (a JSON
    integer of 400 digits is a refusal, not an OverflowError)."""
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise ControlError(key, f"expected a number, got {_short(v)}")
    try:
        x = float(v)
    except OverflowError:
        raise ControlError(key, f"expected a finite number, got an integer of {int(v).bit_length()} bits, "
                                "too large for a float") from None
    if not math.isfinite(x):
        raise ControlError(key, f"expected a finite number, got {x!r}")
    if x < lo or x > hi or (lo_open and x == lo) or (hi_open and x == hi):
        lb = "(" if lo_open else "["
        rb = ")" if hi_open else "]"
        raise ControlError(key, f"expected a number in {lb}{lo:g}, {hi:g}{rb}, got {x:g}")
    return x


_num = number  # the short name used below


def check_size(msg: dict, cmd: str) -> tuple[int, int]:
    """``width`` and ``height`` of an ``open`` or ``resize``: whole pixels in :data:`SIZE_RANGE`."""
    lo, hi = SIZE_RANGE
    out = []
    for k in ("width", "height"):
        v = msg.get(k)
        if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
            raise ControlError(f"{cmd}.{k}", f"expected a whole number of pixels in [{lo}, {hi}], got {_short(v)}")
        out.append(v)
    return out[0], out[1]


def check_keys(msg: dict, allowed: tuple, cmd: str) -> None:
    """Refuse an argument ``cmd`` does not take (naming it and what it takes)."""
    _unknown(msg, allowed, cmd)


def _unknown(msg: dict, allowed: tuple, cmd: str) -> None:
    extra = sorted(set(msg) - set(allowed) - {"cmd"})
    if extra:
        raise ControlError(f"{cmd}.{str(extra[0])[:40]}",
                           f"unknown argument; {cmd} takes {', '.join(allowed) or 'none'}")


def check_style(args: dict, channels: Optional[list[str]], prefix: str = "style") -> dict:
    """Validated style fields. ``channels``: the ring's channels (None = not known here)."""
    _unknown(args, _STYLE_KEYS, prefix)
    out: dict[str, Any] = {}
    for k, v in args.items():
        key = f"{prefix}.{k}"
        if k == "color_by":
            if v is None or v == "none":
                out[k] = None
                continue
            if not isinstance(v, str) or not v:
                raise ControlError(key, f"expected a channel name or one of {', '.join(BUILTIN_COLOR)}, "
                                        f"got {_short(v)}")
            if v not in BUILTIN_COLOR and channels is not None and v not in channels:
                raise ControlError(key, f"channel {_short(v)} is not in the ring (it holds "
                                        f"{sorted(channels) or 'none'}); "
                                   f"to colour by it while running, list it in ring.extra_channels (or start with "
                                   f"render.color_by: {v}) so ingest keeps it")
            out[k] = v
        elif k == "colormap":
            if v not in colormap.NAMES:
                raise ControlError(key, f"unknown colormap {_short(v)}; expected one of {', '.join(colormap.NAMES)}")
            out[k] = v
        elif k == "color_range":
            if v == "auto":
                out[k] = "auto"
                continue
            if not isinstance(v, (list, tuple)) or len(v) != 2:
                raise ControlError(key, f"expected 'auto' or [lo, hi], got {_short(v)}")
            lo, hi = _num(v[0], key), _num(v[1], key)
            if not lo < hi:
                raise ControlError(key, f"expected lo < hi, got [{lo:g}, {hi:g}]")
            out[k] = [lo, hi]
        elif k == "point_size":
            out[k] = _num(v, key, 0.0, MAX_POINT_SIZE_PX, lo_open=True)
        elif k == "point_shape":
            if v not in ("square", "round"):
                raise ControlError(key, f"expected 'square' or 'round', got {_short(v)}")
            out[k] = v
        elif k == "edl":
            if not isinstance(v, bool):
                raise ControlError(key, f"expected true or false, got {_short(v)}")
            out[k] = v
        elif k == "edl_strength":
            out[k] = _num(v, key, 0.0)
        elif k == "time_window_ms":
            out[k] = _num(v, key, 0.0)
    return out


def check_visible(source: Any, on: Any, sources: Optional[list[str]], channels: Optional[list[str]],
                  key: str = "visible") -> bool:
    if not isinstance(on, bool):
        raise ControlError(f"{key}.on", f"expected true or false, got {_short(on)}")
    if not isinstance(source, str):
        raise ControlError(f"{key}.source", f"expected a source name, got {_short(source)}")
    if sources is not None and source not in sources:
        raise ControlError(f"{key}.source", f"no source named {_short(source)}; sources: {', '.join(sources)}")
    if channels is not None and SOURCE_CHANNEL not in channels:
        raise ControlError(f"{key}.source", "this pipeline has one source: there is no other to show alone "
                           "(the ring marks each point's source only with two or more sources)")
    return on


def check_camera(args: dict, prefix: str = "camera") -> dict:
    _unknown(args, _CAMERA_KEYS, prefix)
    out: dict[str, Any] = {}
    for k, v in args.items():
        key = f"{prefix}.{k}"
        out[k] = _num(v, key, 0.0, 180.0, lo_open=True, hi_open=True) if k == "fov_deg" else _vec3(v, key)
    if "up" in out and not any(out["up"]):
        raise ControlError(f"{prefix}.up", "must not be [0, 0, 0]")
    return out


# --------------------------------------------------------------------------- apply
def apply(state: ViewState, msg: Any, *, current: Optional[Camera] = None, channels: Optional[list[str]] = None,
          height_px: int = 720, sources: Optional[list[str]] = None, fixed_frame: Optional[str] = None,
          follow_origin=None) -> ViewState:
    """The state after ``msg``. ``current``: the camera drawn last (turned by orbit/pan/zoom
    and completed by a partial ``camera`` while the mode is auto); ``channels``: the ring's
    channels (``color_by`` must be one of them or a built-in colouring); ``sources``: the
    configured source names (``visible``); ``fixed_frame``: ``frames.fixed`` (``follow``);
    ``follow_origin``: where the followed frame's origin is now, if known."""
    if not isinstance(msg, dict) or not isinstance(msg.get("cmd"), str):
        raise ControlError("cmd", f"a control message is a mapping with 'cmd'; got {_short(msg)}")
    cmd = msg["cmd"]
    args = {k: v for k, v in msg.items() if k != "cmd"}
    new = state.copy()
    if cmd == "view_state":
        _unknown(args, (), cmd)
        return new
    if cmd == "style":
        s = check_style(args, channels, "style")
        if not s:
            return new
        new.style = dataclasses.replace(new.style, **s)
    elif cmd == "visible":
        _unknown(args, ("source", "on"), cmd)
        on = check_visible(args.get("source"), args.get("on", True), sources, channels)
        name = args["source"]
        if on == (name not in state.hidden_sources):
            return new  # already so
        new.hidden_sources = [s for s in state.hidden_sources if s != name] if on else state.hidden_sources + [name]
    elif cmd == "fit":
        _unknown(args, (), cmd)
        new.camera = CameraState(mode="auto", up=list(state.camera.up), fov_deg=state.camera.fov_deg)
    elif cmd == "follow":
        _unknown(args, ("frame",), cmd)
        name = args.get("frame")
        if name is not None and (not isinstance(name, str) or not name.strip()):
            raise ControlError("follow.frame", f"expected a frame name or null, got {_short(name)}")
        if name is not None and not fixed_frame:
            raise ControlError("follow.frame", "following a frame needs frames.fixed in the config (the "
                               "transforms reach the render stage only then; docs/frames.md)")
        base = current if current is not None else _camera_of(state, None)
        if base is None:
            raise ControlError("follow", "nothing is drawn yet: wait for the first frame")
        eye, target = np.asarray(base.eye, np.float64), np.asarray(base.target, np.float64)
        if name is not None and follow_origin is not None:  # keep the view: the offset from the frame now
            eye, target = eye - target + np.asarray(follow_origin, np.float64), np.asarray(follow_origin, np.float64)
        new.camera = CameraState(mode="fixed", eye=list(map(float, eye)), target=list(map(float, target)),
                                 up=list(map(float, base.up)), fov_deg=float(base.fov_deg), follow=name,
                                 follow_anchor=list(map(float, target)) if name is not None else None)
    elif cmd == "camera":
        c = check_camera(args, "camera")
        if not c:
            return new
        base = _camera_of(state, current)
        if base is None and not ("eye" in c and "target" in c):
            raise ControlError("camera.eye", "nothing is drawn yet to start from: give both eye and target")
        cs = new.camera
        cs.mode = "fixed"
        cs.eye = c.get("eye", list(map(float, base.eye)) if base is not None else None)
        cs.target = c.get("target", list(map(float, base.target)) if base is not None else None)
        cs.up = c.get("up", cs.up)
        cs.fov_deg = c.get("fov_deg", cs.fov_deg)
        if np.allclose(cs.eye, cs.target):
            raise ControlError("camera.eye", f"must differ from the target {cs.target}")
        _in_space(cs.eye, cs.target, "camera.eye")
    elif cmd in ("orbit", "pan", "zoom"):
        new.camera = _turn(state, cmd, args, current, height_px)
    else:
        raise ControlError("cmd", f"unknown control message {cmd!r}; expected one of {', '.join(COMMANDS)} "
                                  "(or pick, save)")
    new.version = state.version + 1
    return new


def _turn(state: ViewState, cmd: str, args: dict, current: Optional[Camera], height_px: int) -> CameraState:
    """The camera after an ``orbit``, ``pan`` or ``zoom`` (a move that would leave finite
    space is refused)."""
    keys = {"orbit": ("azimuth_deg", "elevation_deg"), "pan": ("right", "up"), "zoom": ("factor",)}[cmd]
    _unknown(args, keys, cmd)
    vals = {k: _num(args.get(k, 0.0 if cmd != "zoom" else 1.0), f"{cmd}.{k}") for k in keys}
    base = _camera_of(state, current)
    if base is None:
        raise ControlError(cmd, "nothing is drawn yet to turn: wait for the first frame, or set eye and target")
    with np.errstate(all="ignore"):  # an absurd move is refused below, not warned about on the console
        if cmd == "orbit":
            cam = OrbitController(base, orbit_deg_per_px=1.0).orbit(-vals["azimuth_deg"], vals["elevation_deg"])
        elif cmd == "pan":
            cam = OrbitController(base).pan(-vals["right"] * height_px, vals["up"] * height_px, height_px)
        else:
            f = vals["factor"]
            if not f > 0:
                raise ControlError("zoom.factor", f"expected a number > 0, got {f:g}")
            cam = OrbitController(base, zoom_per_wheel=1.0 / f).zoom(1.0)
    _in_space(cam.eye, cam.target, f"{cmd}.{max(keys, key=lambda k: abs(vals[k] - (cmd == 'zoom')))}")
    return CameraState(mode="fixed", eye=list(map(float, cam.eye)), target=list(map(float, cam.target)),
                       up=list(map(float, cam.up)), fov_deg=float(cam.fov_deg), follow=state.camera.follow,
                       follow_anchor=state.camera.follow_anchor)


def _in_space(eye, target, key: str) -> None:
    """A camera stays in finite space: eye and target finite, within MAX_CAMERA_COORD, and
    apart (a move that would leave it is refused, the camera stays where it was)."""
    e, t = np.asarray(eye, np.float64), np.asarray(target, np.float64)
    with np.errstate(all="ignore"):
        ok = (np.isfinite(e).all() and np.isfinite(t).all() and np.abs(e).max() <= MAX_CAMERA_COORD
              and np.abs(t).max() <= MAX_CAMERA_COORD and float(np.linalg.norm(e - t)) > 0.0)
    if not ok:
        raise ControlError(key, f"the camera would leave finite space (eye and target within "
                                f"{MAX_CAMERA_COORD:g} of the origin, apart); it stays where it was")


def _camera_of(state: ViewState, current: Optional[Camera]) -> Optional[Camera]:
    c = state.camera
    if c.mode == "fixed" and c.eye is not None and c.target is not None:
        return Camera(eye=c.eye, target=c.target, up=c.up, fov_deg=c.fov_deg)
    return current


def style_render_config(render_cfg, style: StyleState):
    """``render_cfg`` (a RenderConfig) with the style applied (a new object; the old is untouched)."""
    edl = dataclasses.replace(render_cfg.edl, enabled=bool(style.edl), strength=float(style.edl_strength))
    return dataclasses.replace(render_cfg, color_by=style.color_by, colormap=style.colormap,
                               color_range=style.color_range, point_size=float(style.point_size),
                               point_shape=style.point_shape, time_window_ms=float(style.time_window_ms), edl=edl)


# --------------------------------------------------------------------------- the YAML `view:` block
def view_block(state: ViewState) -> dict:
    """The state as a ``view:`` block (``yaml.safe_dump({"view": view_block(s)})``) that a
    later run starts from."""
    c = state.camera
    cam: Any = "fit" if c.mode == "auto" else {"eye": list(c.eye), "target": list(c.target), "up": list(c.up),
                                               "fov_deg": c.fov_deg}
    out = {"camera": cam, "style": dataclasses.asdict(state.style)}
    if state.hidden_sources:
        out["hidden_sources"] = list(state.hidden_sources)
    return out


def load_view_block(data: Any, path: str = "view") -> dict:
    """Check a ``view:`` block; returns ``{"camera": None | {...}, "style": {...},
    "hidden_sources": [...]}`` with checked values. Errors are :class:`ControlError` naming ``view.<key>``."""
    if not isinstance(data, dict):
        raise ControlError(path, f"expected a mapping with camera and/or style, got {_short(data)}")
    _unknown(data, ("camera", "style", "hidden_sources"), path)
    out: dict[str, Any] = {"camera": None, "style": {}, "hidden_sources": []}
    hs = data.get("hidden_sources") or []
    if not isinstance(hs, list) or not all(isinstance(x, str) for x in hs):
        raise ControlError(f"{path}.hidden_sources", f"expected a list of source names, got {_short(hs)}")
    out["hidden_sources"] = list(hs)
    cam = data.get("camera")
    if cam not in (None, "fit"):
        if not isinstance(cam, dict):
            raise ControlError(f"{path}.camera",
                               f"expected 'fit' or a mapping of eye/target/up/fov_deg, got {_short(cam)}")
        c = check_camera(cam, f"{path}.camera")
        if "eye" not in c or "target" not in c:
            raise ControlError(f"{path}.camera.{'eye' if 'eye' not in c else 'target'}", "required with a fixed camera")
        out["camera"] = c
    st = data.get("style")
    if st is not None:
        if not isinstance(st, dict):
            raise ControlError(f"{path}.style", f"expected a mapping, got {_short(st)}")
        out["style"] = check_style(st, None, f"{path}.style")
    return out
