"""Many views in one render stage: the render side of the view protocol (docs/views.md).

The render stage binds a ROUTER on ``endpoints.views``; a view server (pointflow/serve)
connects a DEALER and opens views for its clients. Each view has its own camera (a
:class:`~pointflow.render.view.controller.ViewController`) and size; the ring is uploaded ONCE per
handoff for the main view and every other view (a second draw passes ``dirty=[]``, so the
tiers that keep their own copy upload nothing; wgpu's one set of point buffers takes a
dirty range once). A view is drawn only when its camera, size, the shared style or the data
changed AND its client has credit (``credit {n}``: it can take n more frames, at most
:data:`~pointflow.render.view.protocol.MAX_CREDIT`): a client that falls behind gets fewer frames and never slows the loop.

Drawing between handoffs (a camera turned while the data stands still) uses the last
handoff's frame with ``dirty=[]``: tiers that keep their data (``Renderer.keeps_data``:
wgpu, the compiled cpu raster) draw at once; the others read the slab and therefore draw
views inside the next handoff (the cadence hands off every tick, also when idle).

The style (colouring, point size, EDL) and the hidden sources are the pipeline's, shared by
all views: they live in what was uploaded, so a per-view style would re-upload per view.
"""
from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np
import zmq

from ...chunk import new_trace_id
from ..base import FrameInput, RenderError, merge_ranges
from . import protocol
from .controller import ViewController
from .mainview import steer
from .protocol import MAX_CREDIT, MAX_MESSAGE_BYTES, MAX_VIEWS, ControlError, check_keys, check_size, point_to_dict
from .legend import camera_dict, follow_dict, legend_dict, view_units

__all__ = ["ViewHub", "View"]

#: Messages read per loop turn (the rest wait for the next turn; the loop never starves).
MAX_MESSAGES_PER_TURN = 256
#: A view whose picture changed within this long is "moving" (the server sends JPEG); when
#: it settles, its last picture goes again as a still frame (the server sends it lossless).
MOVING_S = 0.25
#: How often every connected view server gets a ``stats`` message.
STATS_S = 1.0
#: While views are watched (and no window is open) the main view is drawn at most this
#: often: its picture is read only for PNGs, picks and saves (those redraw it on demand),
#: so the render stage's frames go to the views.
MAIN_WHILE_VIEWED_S = 0.5
#: How often a view frame's legend is computed again while only the data changes: an automatic
#: ``z`` or ``ingest_time`` range is a min/max over every point held (tens of ms per million).
LEGEND_S = 0.5
#: Targets (one per picture size, ``Renderer.resize``) kept besides the main view's: those
#: of the most recently drawn views. Others are freed (``Renderer.forget_sizes``), so a
#: client that resizes again and again, or views that close, leave no memory behind; a
#: view whose size was freed gets a new target on its next draw.
MAX_SIZES_KEPT = 4


@dataclass
class View:
    id: str
    peer: bytes
    width: int
    height: int
    ctl: ViewController  # this view's camera and control state
    credit: int = 0
    seq: int = 0
    frames: int = 0
    skipped_no_credit: int = 0
    bytes_sent: int = 0
    drawn_key: Any = None
    changed_t: float = 0.0
    sent_moving: bool = False
    last_image: Optional[np.ndarray] = None
    last_header: dict = field(default_factory=dict)
    waiting: bool = False  # a change is waiting for credit (counted once per change)
    t_drawn: float = 0.0  # when it was last drawn (the sizes kept are the latest views')


class ViewHub:
    """The views of one render stage and the ROUTER they come through."""

    def __init__(self, ctx, sock, cfg, channels: list[str]):
        self.ctx = ctx
        self.sock = sock
        self.cfg = cfg
        self.channels = channels
        self.sources = [s.name for s in cfg.sources]
        self.views: dict[str, View] = {}
        self.peers: dict[bytes, float] = {}  # view servers heard from, and when
        self.last_frame: Optional[FrameInput] = None
        self.data_gen = 0
        self._data_sig: Any = None
        self._unconsumed = False  # last_frame's dirty ranges not drawn by anyone yet
        #: dirty ranges of handoffs nobody drew (None = all): a later slab holds those slots'
        #: newer contents, so the next draw takes them from there
        self._carry: Any = []
        self.clobbered = False  # the renderer's target holds a view's picture, not main's
        self._legend_key: Any = None  # the legend of view frames (_legend): style, data generation, when
        self._legend_gen, self._legend_t, self._legend_val = -1, 0.0, None
        self.totals = {"view_frames": 0, "view_skipped_no_credit": 0, "view_bytes": 0, "view_uploaded_bytes": 0}
        self._t_stats = time.monotonic()
        self._main_frames0 = 0
        self._view_frames0 = 0
        self.draw_ms_ema = 0.0
        self.t_main = 0.0  # when the main view was last drawn

    @classmethod
    def open(cls, ctx, cfg, channels: list[str]) -> Optional["ViewHub"]:
        ep = getattr(ctx.endpoints, "views", None)
        if not ep:
            return None
        sock = ctx.zmq.socket(zmq.ROUTER)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.ROUTER_MANDATORY, 1)  # a gone view server raises, its views close
        sock.setsockopt(zmq.MAXMSGSIZE, MAX_MESSAGE_BYTES)
        sock.setsockopt(zmq.SNDHWM, MAX_CREDIT * MAX_VIEWS + 64)
        sock.bind(ep)
        return cls(ctx, sock, cfg, channels)

    # ------------------------------------------------------------------ messages
    def service(self, stage, ring) -> None:
        """Read the view servers' messages, draw what changed (tiers that keep their data),
        send stats. Called once per loop turn of the render stage."""
        for _ in range(MAX_MESSAGES_PER_TURN):
            try:
                parts = self.sock.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                break
            self._message(parts, stage, ring)
        renderer = stage.renderer
        if self.views and self.last_frame is not None and renderer.keeps_data:
            self._draw_all(stage, self.last_frame)
        self._resend_still()
        self._legend_catch_up(stage)
        now = time.monotonic()
        if now - self._t_stats >= STATS_S:
            self._stats(stage, now)

    def _bad(self, peer: Optional[bytes], view: Optional[str], req: Any, exc: Exception, key: str,
             reply: Optional[dict] = None) -> None:
        self.ctx.counters.drop("bad_view_message", 1)
        n = self.ctx.counters.drops.get("bad_view_message", 0)
        if n <= 10 or n % 1000 == 0:
            self.ctx.log.warning("view message refused (%d so far): %s", n, exc)
        if peer is not None:
            self._send(peer, reply or {"type": "error", "view": view, "req": req, "error": str(exc), "key": key})

    def _message(self, parts: list, stage, ring) -> None:
        peer = parts[0] if parts else None
        if len(parts) != 2:
            self._bad(peer, None, None, ValueError(f"expected one JSON frame, got {len(parts) - 1} frames"), "message")
            return
        try:
            msg = json.loads(parts[1])
        except ValueError as exc:
            self._bad(peer, None, None, ValueError(f"not JSON: {exc}"), "message")
            return
        self.peers[peer] = time.monotonic()
        if not isinstance(msg, dict):
            self._bad(peer, None, None, ValueError(f"expected a JSON object, got {type(msg).__name__}"), "message")
            return
        vid, cmd, req = msg.get("view"), msg.get("cmd"), msg.get("req")
        if req is not None and (isinstance(req, bool) or not isinstance(req, int)):
            self._bad(peer, None, None, ValueError(f"req: expected an integer, got {req!r}"), "req")
            return
        if not isinstance(vid, str) or not vid or len(vid) > 128:
            self._bad(peer, None, req, ValueError(f"view: expected a view id (a string), got {vid!r}"), "view")
            return
        if not isinstance(cmd, str):
            self._bad(peer, vid, req, ValueError(f"cmd: expected a command name, got {cmd!r}"), "cmd")
            return
        if cmd == "ping":
            return
        try:
            self._command(peer, vid, cmd, req, msg, stage, ring)
        except ControlError as exc:
            self._bad(peer, vid, req, exc, exc.key)
        except Exception as exc:  # noqa: BLE001 - no message a view server relays may stop the render stage
            self._bad(peer, vid, req, ControlError(cmd, f"{type(exc).__name__}: {exc}"), cmd)

    def _command(self, peer: bytes, vid: str, cmd: str, req, msg: dict, stage, ring) -> None:
        if cmd == "open":
            check_keys({k: v for k, v in msg.items() if k not in ("view", "req")},
                       ("width", "height", "state", "seq"), "open")
            w, h = check_size(msg, "open")
            seq = msg.get("seq", 0)  # a view opened again after a restart numbers on from the server's last
            if isinstance(seq, bool) or not isinstance(seq, int) or not 0 <= seq < 2 ** 53:
                raise ControlError("open.seq", f"expected a whole number >= 0, got {seq!r}")
            if vid not in self.views and len(self.views) >= MAX_VIEWS:
                raise ControlError("open", f"this render stage serves at most {MAX_VIEWS} views")
            v = self._new_view(vid, peer, w, h, stage)
            v.seq = seq
            if msg.get("state") is not None:
                try:
                    self._take_state(v, msg["state"])
                except ControlError as exc:  # the view opens framed on the data: better than not at all
                    self._bad(None, vid, req, exc, exc.key)
            self.views[vid] = v
            self._trim_sizes(stage)
            self._reply(v, req)
            self.ctx.log.info("view %s open (%dx%d)", vid, w, h)
            return
        v = self.views.get(vid)
        if v is None and cmd == "close":  # closed already (the page went, then the server stopped): done
            return
        if v is None:  # a restarted render stage, or a closed view: the client opens it again
            # not bad input: a message in flight when its page went (killed), or from before a
            # restart; counted and answered "gone", logged at debug (it warned at every stop)
            ex = self.ctx.counters.extra
            ex["view_gone_messages"] = ex.get("view_gone_messages", 0) + 1
            self.ctx.log.debug("view message for a view not open here (%s %s): answered gone", vid, cmd)
            self._send(peer, protocol.gone_reply(vid, req))
            return
        v.peer = peer
        args = {k: val for k, val in msg.items() if k not in ("view", "req")}
        if cmd == "close":
            self._close(vid)
            self._trim_sizes(stage)
        elif cmd == "credit":
            check_keys(args, ("n",), "credit")
            n = args.get("n")
            if isinstance(n, bool) or not isinstance(n, int) or n < 0:
                raise ControlError("credit.n", f"expected a whole number >= 0, got {n!r}")
            v.credit = min(n, MAX_CREDIT)
        elif cmd == "resize":
            check_keys(args, ("width", "height"), "resize")
            v.width, v.height = check_size(args, "resize")
            v.ctl.auto.aspect = v.width / v.height
            v.ctl.height = v.height
            self._trim_sizes(stage)
            self._reply(v, req)
        elif cmd == "pick":
            check_keys(args, ("x", "y", "pixel_ratio"), "pick")
            x, y = protocol.number(args.get("x"), "pick.x"), protocol.number(args.get("y"), "pick.y")
            pr = protocol.number(args.get("pixel_ratio", 1.0), "pick.pixel_ratio", 0.0, 16.0, lo_open=True)
            self._pick(v, x, y, pr, req, stage, ring)
        elif cmd in ("style", "visible"):  # the pipeline's, shared by every view (module docstring)
            steer(dict(args, cmd=cmd), stage, self.ctx)
            main = stage.view.state
            st = v.ctl.state.copy()
            st.style, st.hidden_sources = dataclasses.replace(main.style), list(main.hidden_sources)
            st.version += 1
            v.ctl.state = st
            self._reply(v, req)
        elif cmd in protocol.COMMANDS:
            v.ctl.apply(args | {"cmd": cmd}, None)
            self._reply(v, req)
        else:
            raise ControlError("cmd", f"unknown view command {cmd!r}; expected open, close, resize, credit, pick "
                                      f"or one of {', '.join(protocol.COMMANDS)}")

    def _new_view(self, vid: str, peer: bytes, w: int, h: int, stage) -> View:
        ctl = ViewController(self.cfg, w, h, self.channels)
        ctl.state.style = dataclasses.replace(stage.view.state.style)
        ctl.state.hidden_sources = list(stage.view.state.hidden_sources)
        return View(id=vid, peer=peer, width=w, height=h, ctl=ctl, changed_t=time.monotonic())

    def _take_state(self, v: View, state: Any) -> None:
        """An ``open`` with a state (a reply's ViewState dict): its camera."""
        if not isinstance(state, dict) or not isinstance(state.get("camera"), dict):
            raise ControlError("open.state", "expected a view state (a reply's dict with 'camera')")
        cam = state["camera"]
        if cam.get("mode") == "fixed" and cam.get("eye") is not None and cam.get("target") is not None:
            v.ctl.apply({"cmd": "camera", "eye": cam["eye"], "target": cam["target"],
                         "up": cam.get("up", [0.0, 0.0, 1.0]), "fov_deg": cam.get("fov_deg", 60.0)}, None)

    def _reply(self, v: View, req) -> None:
        d = v.ctl.reply(None, v.frames)
        d.pop("view_block", None)
        self._send(v.peer, {"type": "reply", "view": v.id, "req": req, "width": v.width, "height": v.height, **d})

    def _trim_sizes(self, stage) -> None:
        """Free the renderer's targets of sizes no open view needs (MAX_SIZES_KEPT)."""
        recent = sorted(self.views.values(), key=lambda v: v.t_drawn, reverse=True)
        keep = {tuple(self.cfg.render.size)}
        for v in recent:
            if len(keep) > MAX_SIZES_KEPT:
                break
            keep.add((v.width, v.height))
        freed = stage.renderer.forget_sizes(keep)
        if freed:
            ex = self.ctx.counters.extra
            ex["view_targets_freed"] = ex.get("view_targets_freed", 0) + freed

    def _close(self, vid: str) -> None:
        v = self.views.pop(vid, None)
        if v is not None:
            self.ctx.log.info("view %s closed after %d frames", vid, v.frames)
        self._counters()

    # ------------------------------------------------------------------ drawing
    def _take_carry(self, frame: FrameInput) -> None:
        if self._carry == []:
            return
        if self._carry is None or frame.dirty is None:
            frame.dirty = None
        else:
            frame.dirty = merge_ranges(list(self._carry) + list(frame.dirty), frame.capacity)
        self._carry = []

    def main_rests(self, window, frame: FrameInput) -> bool:
        """True when the main view skips this handoff (views are open, no window, and main
        was drawn lately): the views draw it instead (:meth:`handoff`). Also gives ``frame``
        the dirty ranges of earlier handoffs that nobody drew."""
        self._take_carry(frame)
        return window is None and bool(self.views) and time.monotonic() - self.t_main < MAIN_WHILE_VIEWED_S

    def handoff(self, frame: FrameInput, main_drew: bool, stage) -> None:
        """A handoff (its slab still held): keep it for drawing between handoffs. Views draw
        now when main did not take the new data (it rests) or when the tier reads the slab
        at every draw; after those, main draws again (its picture is the one PNGs, picks
        and saves read)."""
        if main_drew:
            self.t_main = time.monotonic()
        else:
            self._take_carry(frame)
        sig = (frame.head, frame.size, tuple(np.round(frame.origin, 9)))
        if frame.dirty is None or frame.dirty or sig != self._data_sig:
            self.data_gen += 1
        self._data_sig = sig
        self._unconsumed = not main_drew and frame.dirty != []
        self.last_frame = frame
        if not self.views or (stage.renderer.keeps_data and not self._unconsumed):
            return
        drew = self._draw_all(stage, frame)
        if drew and main_drew and stage.view.last is not None:
            self.restore_main(stage)
        if self._unconsumed:  # new data nobody drew before its slab goes back: the next draw takes it
            self._unconsumed = False
            self._carry = None if frame.dirty is None else list(frame.dirty)

    def restore_main(self, stage) -> None:
        """Draw main's picture again (from the data already uploaded) when a view's is in
        the target: before a pick or save of the main view."""
        if not self.clobbered or self.last_frame is None or stage.view.last is None:
            return
        r = stage.renderer
        r.resize(*self.cfg.render.size)
        r.render(dataclasses.replace(self.last_frame, dirty=[]), stage.view.last)
        self.clobbered = False

    def _frame_for_draw(self) -> FrameInput:
        f = self.last_frame
        if self._unconsumed:
            self._unconsumed = False
            return f
        return dataclasses.replace(f, dirty=[])

    def _draw_all(self, stage, frame: FrameInput) -> bool:
        now = time.monotonic()
        drew = False
        style = (stage.view.state.style, tuple(stage.view.state.hidden_sources), id(stage.renderer))
        for v in list(self.views.values()):
            try:
                cam = v.ctl.camera(frame)
            except Exception as exc:  # noqa: BLE001 - one view's camera must not stop the others
                self.ctx.log.warning("view %s: no camera (%s)", v.id, exc)
                continue
            if cam is None:
                continue
            key = (self.data_gen, v.ctl.state.version, style, cam.view_proj(16, 9).tobytes(), cam.near, cam.far,
                   v.width, v.height)
            if key == v.drawn_key and not stage.view.state.style.time_window_ms > 0:
                v.waiting = False
                continue
            if v.credit <= 0:
                if not v.waiting:
                    v.waiting = True
                    v.skipped_no_credit += 1
                    self.totals["view_skipped_no_credit"] += 1
                continue
            if self._draw(v, stage, cam, key, now):
                drew = True
        if drew:
            self._counters()
        return drew

    def _render(self, v: View, stage, cam) -> tuple[np.ndarray, float]:
        r = stage.renderer
        t0 = time.perf_counter()
        t0_ns = time.monotonic_ns()
        if not r.resize(v.width, v.height):
            v.width, v.height = r.width, r.height  # the tier draws one size: the client scales
        try:
            fs = r.render(self._frame_for_draw(), cam)
            img = r.read_image()
            self.totals["view_uploaded_bytes"] += int(fs.uploaded_bytes)
        finally:
            r.resize(*self.cfg.render.size)
        self.clobbered = True
        v.t_drawn = time.monotonic()
        if len(getattr(r, "_targets", ())) > MAX_SIZES_KEPT + 1:
            self._trim_sizes(stage)
        # one "view_draw" slice per view frame in the profile trace (draw + read-back)
        self.ctx.spans.record(new_trace_id(), "view_draw", t0_ns, time.monotonic_ns(), int(self.last_frame.size))
        return img, (time.perf_counter() - t0) * 1e3

    def _legend(self, stage) -> Optional[dict]:
        """The colour legend of the pictures drawn from the last handoff (render/view/legend.py):
        at once after a style change, at most every LEGEND_S while only the data changes."""
        style = stage.view.state.style
        units = view_units(getattr(stage, "maplayer", None))
        k = (style.color_by, style.colormap, str(style.color_range), units["z"])
        now = time.monotonic()
        # new data alone: at most every LEGEND_S (an automatic z range reads every position)
        if self._legend_key != k or (self._legend_gen != self.data_gen and now - self._legend_t >= LEGEND_S):
            self._legend_key, self._legend_gen, self._legend_t = k, self.data_gen, now
            self._legend_val = legend_dict(self.last_frame, style, units)
        return self._legend_val

    def _legend_catch_up(self, stage) -> None:
        """New data came within LEGEND_S of the last legend and nothing has been drawn since
        (the data stopped): the views get the legend of what they show as its own message."""
        if not self.views or self._legend_key is None or self._legend_gen == self.data_gen \
                or time.monotonic() - self._legend_t < LEGEND_S:
            return
        old = self._legend_val
        if self._legend(stage) != old:
            for v in list(self.views.values()):
                if v.frames:
                    self._send(v.peer, {"type": "legend", "view": v.id, "legend": self._legend_val})

    def _draw(self, v: View, stage, cam, key, now: float) -> bool:
        try:
            img, ms = self._render(v, stage, cam)
        except (ValueError, RenderError) as exc:
            self.ctx.counters.drop("view_render_error", 1)
            self.ctx.log.warning("view %s not drawn: %s", v.id, exc)
            return False
        v.ctl.last = cam
        v.ctl._pending_key = None
        v.ctl.drawn()
        if key != v.drawn_key:
            v.changed_t = now
        v.drawn_key = key
        v.waiting = False
        moving = now - v.changed_t < MOVING_S and v.frames > 0
        h, w = img.shape[:2]
        v.seq += 1
        hdr = {"type": "frame", "view": v.id, "seq": v.seq, "width": int(w), "height": int(h), "moving": moving,
               "version": v.ctl.state.version, "points": int(self.last_frame.size), "frame_ms": round(ms, 3),
               "t_ns": time.monotonic_ns(), "camera": camera_dict(cam), "legend": self._legend(stage),
               "follow": follow_dict(v.ctl), "units": view_units(getattr(stage, "maplayer", None))}
        self.draw_ms_ema = ms if not self.draw_ms_ema else 0.9 * self.draw_ms_ema + 0.1 * ms
        data = np.ascontiguousarray(img)  # read_image's own copy: sent without another (zmq copy=False)
        if not self._send(v.peer, hdr, data):
            return True
        v.last_image, v.last_header = data, hdr
        v.sent_moving = moving
        v.credit -= 1
        v.frames += 1
        v.bytes_sent += data.nbytes
        self.totals["view_frames"] += 1
        self.totals["view_bytes"] += data.nbytes
        return True

    def _resend_still(self) -> None:
        """A view that stopped moving gets its last picture again, marked still (lossless)."""
        now = time.monotonic()
        for v in list(self.views.values()):
            if v.sent_moving and v.credit > 0 and now - v.changed_t >= MOVING_S and v.last_image is not None:
                v.seq += 1
                hdr = dict(v.last_header, seq=v.seq, moving=False, t_ns=time.monotonic_ns())
                if self._send(v.peer, hdr, v.last_image):
                    v.sent_moving = False
                    v.credit -= 1
                    v.frames += 1
                    v.bytes_sent += v.last_image.nbytes
                    self.totals["view_frames"] += 1
                    self.totals["view_bytes"] += v.last_image.nbytes

    def _pick(self, v: View, x: float, y: float, pr: float, req, stage, ring) -> None:
        """Draw the view's picture (from the data uploaded) and pick in it."""
        if self.last_frame is None:
            raise ControlError("pick", "nothing is drawn yet: wait for the first frame")
        cam = v.ctl.camera(self.last_frame)
        if cam is None:
            raise ControlError("pick", "nothing is drawn yet: wait for the first frame")
        r = stage.renderer
        if not r.resize(v.width, v.height):
            pass
        try:
            r.render(self._frame_for_draw(), cam)
            slot = r.pick(x, y, pr)
        finally:
            r.resize(*self.cfg.render.size)
            self.clobbered = True
        if stage.maplayer is not None:  # a map point is named "map: <file>", a live one by its source
            rep = stage.maplayer.pick_reply(ring, slot, point_to_dict)
            self._send(v.peer, {"type": "pick", "view": v.id, "req": req, "point": rep.get("point"),
                                "source": rep.get("source")})
            return
        point = point_to_dict(ring.get_point(slot)) if slot is not None else None
        source = None
        if point is not None:
            idx = point["channels"].get(protocol.SOURCE_CHANNEL)
            if idx is not None and 0 <= int(idx) < len(self.sources):
                source = self.sources[int(idx)]
            elif len(self.sources) == 1:
                source = self.sources[0]
        self._send(v.peer, {"type": "pick", "view": v.id, "req": req, "point": point, "source": source})

    # ------------------------------------------------------------------ sending, stats
    def _send(self, peer: bytes, header: dict, payload: Any = b"") -> bool:
        try:
            self.sock.send_multipart([peer, json.dumps(header).encode(), payload], zmq.NOBLOCK, copy=False)
            return True
        except zmq.Again:  # the view server's queue is full: this frame is dropped, counted
            self.ctx.counters.drop("view_send_full", 1)
        except zmq.ZMQError as exc:
            if exc.errno == zmq.EHOSTUNREACH:  # the view server is gone: its views too
                self.peers.pop(peer, None)
                for vid in [k for k, v in self.views.items() if v.peer == peer]:
                    self._close(vid)
                self.ctx.counters.drop("view_peer_gone", 1)
            else:
                raise
        return False

    def _counters(self) -> None:
        ex = self.ctx.counters.extra
        ex.update(self.totals)
        ex["views_open"] = len(self.views)
        ex["views"] = {v.id: {"frames": v.frames, "skipped_no_credit": v.skipped_no_credit, "bytes": v.bytes_sent,
                              "size": [v.width, v.height], "credit": v.credit} for v in self.views.values()}
        ex["view_draw_ms_ema"] = round(self.draw_ms_ema, 3)

    def _stats(self, stage, now: float) -> None:
        dt = now - self._t_stats
        self._t_stats = now
        main = int(self.ctx.counters.extra.get("frames", 0))
        vf = self.totals["view_frames"]
        vfps = (vf - self._view_frames0) / dt if dt > 0 else 0.0
        fps = (main - self._main_frames0) / dt + vfps if dt > 0 else 0.0  # every picture the stage drew
        self._main_frames0, self._view_frames0 = main, vf
        self._counters()
        self.ctx.counters.extra["view_targets_kept"] = len(getattr(stage.renderer, "_targets", None) or {}) or 1
        drops = {k: v for k, v in self.ctx.counters.drops.items() if v}
        points = int(self.last_frame.size) if self.last_frame is not None else 0
        if stage.maplayer is not None and self.last_frame is not None and self.last_frame.live_slots is not None:
            points -= stage.maplayer.empty_slots  # a map's frame has a slot for every point it could hold
        msg = {"type": "stats", "points": max(points, 0),
               "fps": round(fps, 2), "view_fps": round(vfps, 2), "sources": self.sources, "drops": drops,
               "tier": stage.renderer.tier, "views": self.ctx.counters.extra.get("views", {})}
        for peer, t in list(self.peers.items()):
            if now - t > 30.0 and not any(v.peer == peer for v in self.views.values()):
                self.peers.pop(peer, None)  # a view server not heard from for 30 s
                continue
            self._send(peer, msg)

    def close(self) -> None:
        self.sock.close(0)
