"""The notebook view: one view of a running pipeline's render stage as an anywidget.

The widget is a client of the view protocol (docs/views.md), like the view server: a zmq
DEALER on the render stage's ``endpoints.views``, opening a view of its own with its own
camera. Frames travel to the browser over the widget's comm (the kernel's own channel), not
over a port of their own: that works wherever the notebook works (JupyterLab, Notebook,
VS Code, a remote kernel behind a proxy) and exposes nothing new on the network. A thread
of the kernel receives the frames, encodes them as the view server does (JPEG while moving,
PNG when still: :mod:`pointflow.render.view.encode`) and sends each with ``Widget.send``; the
browser acknowledges each frame drawn, and at most two are in flight (the render stage
draws for this view only when the widget can take a frame).

The timeline steers the pipeline's replaying sources through ``Pipeline.playback`` (in a
thread of its own: a seek waits until it has landed, and frames go on meanwhile). The kernel
side also watches the pipeline: once it stops (``p.stop()``, a failure, the window closed),
:attr:`LiveView.stopped` says why and the page shows "run ended" with its controls off.
"""
from __future__ import annotations

import json
import pathlib
import queue
import secrets
import threading
import time
from typing import Any, Optional

import anywidget
import traitlets
import zmq

from ..render.view import GESTURES_JS, OVERLAY_JS
from ..render.view.client import ClientEnd
from ..render.view.encode import encode_frame
from ..render.view.protocol import COLORMAPS, COMMANDS, color_by_options
from ..render.view.legend import lut_hex

__all__ = ["LiveView"]

STATIC = pathlib.Path(__file__).parent / "static"
#: What the timeline may ask of ``Pipeline.playback`` (the page's timeline: serve/server.py).
PLAYBACK_KEYS = ("paused", "seek_s", "seek_fraction", "step", "rate", "loop")


def _replays(cfg) -> list[str]:
    """The names of the pipeline's replaying sources (those ``Pipeline.playback`` steers)."""
    from ..ingest.transports import resolve_transport

    return [s.name for s in cfg.sources
            if not s.external and getattr(resolve_transport(s.transport), "seekable", False)]


class LiveView(anywidget.AnyWidget):
    """A live view of ``pipeline`` (started, with the render stage's ``endpoints.views``)."""

    #: the page's gestures and overlay (axes, grid, compass, legend, marks: render/view/static,
    #: one file each for both) and the widget's own module
    _esm = "\n".join(f.read_text() for f in (GESTURES_JS, OVERLAY_JS, STATIC / "widget.js"))
    _css = STATIC / "widget.css"
    width = traitlets.Int(640).tag(sync=True)
    height = traitlets.Int(400).tag(sync=True)
    color_by_options = traitlets.List(traitlets.Unicode()).tag(sync=True)
    colormaps = traitlets.List(traitlets.Unicode()).tag(sync=True)
    #: each colormap's 256 RGB entries as hex (the legend bar: the render stage's own table)
    luts = traitlets.Dict().tag(sync=True)
    #: the replaying sources (``file``, ``rosbag``): the page shows the timeline when any
    replays = traitlets.List(traitlets.Unicode()).tag(sync=True)
    #: "" while the pipeline runs; why it ended once it stopped ("run ended", "run failed: ...")
    stopped = traitlets.Unicode("").tag(sync=True)

    def __init__(self, pipeline, *, width: int = 640, height: int = 400, owns_pipeline: bool = False):
        sup = pipeline.supervisor
        if sup is None or not pipeline.running:
            raise RuntimeError("LiveView: start the pipeline first (Pipeline.start())")
        cfg = pipeline.cfg
        chans = color_by_options(cfg.ring_channels())
        super().__init__(width=int(width), height=int(height), color_by_options=chans, colormaps=list(COLORMAPS),
                         replays=_replays(cfg), luts={n: lut_hex(n) for n in COLORMAPS})
        self.pipeline = pipeline
        self.owns_pipeline = owns_pipeline
        self.view_id = f"nb-{secrets.token_hex(4)}"
        self.endpoint = sup.endpoints.views
        #: counters (also for tests): frames from render, frames acknowledged by the browser
        self.frames_received = 0
        self.frames_acked = 0
        self.bytes_sent = 0
        self.last_encode_ms = 0.0
        self.last_pick: Optional[dict] = None
        self.last_reply: Optional[dict] = None
        self.views_reopened = 0  # times the render stage restarted and the view was opened again
        self.playback_refused = 0  # timeline requests refused (each answered with the key at fault)
        self._inbox: "queue.SimpleQueue[dict]" = queue.SimpleQueue()
        self._playback_q: "queue.SimpleQueue[Optional[dict]]" = queue.SimpleQueue()
        self._playback_thread: Optional[threading.Thread] = None
        self._stop = threading.Event()
        self.on_msg(self._on_browser)
        self._thread = threading.Thread(target=self._run, name=f"pointflow-view-{self.view_id}", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ browser -> kernel
    def _on_browser(self, _widget, content: Any, _buffers) -> None:
        if isinstance(content, dict):
            self._inbox.put(content)

    # ------------------------------------------------------------------ the link to render
    def _run(self) -> None:
        sock = zmq.Context.instance().socket(zmq.DEALER)
        sock.setsockopt(zmq.LINGER, 0)
        sock.connect(self.endpoint)
        link = _Link(self, sock)
        try:
            link.open()
            while not self._stop.is_set():
                link.browser()
                if sock.poll(20):
                    link.render(sock.recv_multipart())
                link.keepalive()
                why = self._ended()
                if why:  # the frames stop; the page keeps the last one and says why
                    self.stopped = why
                    break
            else:
                link.send(cmd="close")
        except zmq.ZMQError:  # the context went away with the kernel
            pass
        finally:
            sock.close(0)
            self._playback_q.put(None)

    def _ended(self) -> str:
        """Why the pipeline is no longer running ("" while it runs)."""
        p = self.pipeline
        sup = p.supervisor
        if sup is not None and p.running:
            return ""
        try:
            final = p.stats()
        except RuntimeError:  # it never ran
            final = {}
        failure = getattr(sup, "failure", None) or final.get("failure")
        return f"run failed: {str(failure)[:200]}" if failure else "run ended"

    # ------------------------------------------------------------------ the timeline
    def _playback(self, m: dict) -> None:
        """A timeline request from the page: answered by a thread of its own (a seek waits
        until it has landed; the frames go on meanwhile)."""
        if self._playback_thread is None:
            self._playback_thread = threading.Thread(target=self._playback_loop, daemon=True,
                                                     name=f"pointflow-playback-{self.view_id}")
            self._playback_thread.start()
        self._playback_q.put(m)

    def _playback_loop(self) -> None:
        from ..ingest.playback import PlaybackError

        while True:
            m = self._playback_q.get()
            if m is None or self._stop.is_set():
                return
            args = m.get("args", {})
            try:
                if not isinstance(args, dict):
                    raise PlaybackError("args", f"expected an object of {', '.join(PLAYBACK_KEYS)}, got {str(args)[:60]!r}")
                bad = [k for k in args if k not in PLAYBACK_KEYS]
                if bad:
                    raise PlaybackError(str(bad[0])[:60], f"unknown argument; the timeline sends {', '.join(PLAYBACK_KEYS)}")
                out = self.pipeline.playback(**args, timeout_s=3.0)
                self.send({"type": "playback", "req": m.get("req"), "sources": out})
            except PlaybackError as exc:
                self.playback_refused += 1
                self.send({"type": "error", "req": m.get("req"), "key": f"playback.{exc.key}",
                           "error": exc.message})
            except (RuntimeError, TimeoutError) as exc:  # ended, restarting, or not landed in time
                self.send({"type": "error", "req": m.get("req"), "key": "playback", "error": str(exc)})

    def close(self) -> None:
        """Close the view (and the pipeline, when :func:`pointflow.show` started it for this widget)."""
        self._stop.set()
        self._thread.join(timeout=2.0)
        super().close()
        if self.owns_pipeline:
            self.pipeline.stop()


class _Link:
    """The widget thread's state: the view's client end (credit, frame numbers, camera:
    render/view/client.py, as the view server keeps it) and the frames the browser holds."""

    def __init__(self, w: LiveView, sock):
        self.w, self.sock = w, sock
        self.in_flight: dict[int, float] = {}  # seq -> when sent to the browser
        self.end = ClientEnd(w.width, w.height, granted=-1)
        self.req = 0
        self.t_ping = 0.0
        self.enc_ms: list[float] = []
        self.sizes: list[int] = []
        self.acks: list[float] = []  # when the browser drew each frame (the last 2 s)

    def send(self, **msg) -> None:
        try:
            self.sock.send(json.dumps({"view": self.w.view_id, **msg}).encode(), zmq.NOBLOCK)
        except zmq.Again:
            pass

    def open(self, again: bool = False) -> None:
        """Open the view; ``again`` after a render restart: with its camera and a frame
        number past every frame seen (as the view server does), so nothing is taken for old."""
        self.end.width, self.end.height = self.w.width, self.w.height
        self.send(**self.end.open(again=again))
        self.send(cmd="view_state", req=self._req())
        self.grant()

    def _req(self) -> int:
        self.req += 1
        return self.req

    def grant(self, again: bool = False) -> None:
        now = time.monotonic()
        for seq, t in list(self.in_flight.items()):  # a frame the browser never drew (output cleared)
            if now - t > 10.0:
                del self.in_flight[seq]
        msg = self.end.credit(len(self.in_flight), again=again)
        if msg is not None:
            self.send(**msg)

    def keepalive(self) -> None:
        now = time.monotonic()
        if now - self.t_ping > 1.0:
            self.t_ping = now
            self.grant(again=True)  # also re-grants after a render stage restart

    def browser(self) -> None:
        while True:
            try:
                m = self.w._inbox.get_nowait()
            except queue.Empty:
                return
            kind = m.get("type")
            if kind == "ack":
                if self.in_flight.pop(m.get("seq"), None) is not None:
                    self.w.frames_acked += 1
                    now = time.monotonic()
                    self.acks = [t for t in self.acks if now - t < 2.0] + [now]
                self.grant()
            elif kind == "hello":  # a (new) display of the widget: it has drawn nothing yet
                self.in_flight.clear()
                self.send(cmd="view_state", req=self._req())
                self.grant(again=True)
            elif kind == "control" and isinstance(m.get("msg"), dict) and m["msg"].get("cmd") in COMMANDS:
                self.send(**{k: v for k, v in m["msg"].items() if k not in ("view", "req")}, req=self._req())
            elif kind == "pick":
                self.send(cmd="pick", x=m.get("x"), y=m.get("y"), req=self._req())
            elif kind == "playback":  # the timeline: Pipeline.playback, in a thread of its own
                self.w._playback(m)

    def render(self, parts: list) -> None:
        if len(parts) != 2:
            return
        head = json.loads(parts[0])
        kind = head.get("type")
        what = self.end.from_render(head)  # credit used, frame numbers, the camera of a reply
        w = self.w
        if what == "frame":
            w.frames_received += 1
            enc = encode_frame(parts[1], head["width"], head["height"], bool(head.get("moving")))
            self.enc_ms = (self.enc_ms + [enc.encode_ms])[-60:]
            self.sizes = (self.sizes + [len(enc.data)])[-60:]
            w.last_encode_ms = enc.encode_ms
            w.bytes_sent += len(enc.data)
            self.in_flight[head["seq"]] = time.monotonic()
            w.send({"type": "frame", "seq": head["seq"], "mime": enc.mime, "version": head.get("version"),
                    "width": head["width"], "height": head["height"], "moving": head.get("moving"),
                    **{k: head[k] for k in ("camera", "legend", "follow", "units") if k in head}}, [enc.data])
        elif what == "gone":
            self.in_flight.clear()  # the render stage restarted: open the view again, as it was
            self.w.views_reopened += 1
            self.open(again=True)
        elif what == "stats":
            n = len(self.sizes)
            w.send({"type": "stats", "points": head.get("points"), "fps": head.get("fps"),
                    "view_fps": round(len([t for t in self.acks if time.monotonic() - t < 2.0]) / 2.0, 1),
                    "bytes_per_frame": sum(self.sizes) / n if n else 0,
                    "encode_ms": round(sum(self.enc_ms) / len(self.enc_ms), 2) if self.enc_ms else 0,
                    "sources": head.get("sources", [])})
        elif kind == "legend":  # the data changed after the last frame (render/view/hub.py)
            w.send({"type": "legend", "legend": head.get("legend")})
        elif kind in ("reply", "pick", "error"):
            if kind == "pick":
                w.last_pick = head
            elif kind == "reply":
                w.last_reply = head
            w.send(head)
