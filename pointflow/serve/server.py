"""The view server: one page, one WebSocket per browser tab, one view per WebSocket.

Between the browser and the render stage (docs/views.md):

* to render, a zmq DEALER on ``endpoints.views`` (the render stage's ROUTER): ``open`` /
  ``close`` / ``resize`` / ``credit`` and the control messages of render/control.py, each
  ``{"view": id, "cmd": ...}``;
* from render, ``[header, RGBA]`` frames (drawn only when the view changed and has credit),
  replies, picks, errors and stats;
* to the browser, each frame encoded in a thread pool (JPEG while moving, PNG when still) as
  one binary message: a 4-byte big-endian header length, the JSON header, the image;
  replies, picks, stats and errors as JSON text messages.

Flow: a view has at most :data:`MAX_IN_FLIGHT` frames between "credit given to render" and
"shown by the page" (the page acks each frame it has drawn); a newer frame replaces the
oldest still waiting for a slow client (counted ``dropped_frames``). A client that never
reads fills only its own bounded queue and is closed after ``limits.send_timeout_s``. A
malformed, oversized or too frequent message closes that client only and is counted.
Playback (the replay timeline) goes to the replaying sources' own endpoints, as
``Pipeline.playback`` does.
"""
from __future__ import annotations

import asyncio
import collections
import json
import logging
import os
import secrets
import socket as socketlib
import ssl
import struct
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from importlib.resources import files as resource_files
from typing import Any, Optional

import zmq
import zmq.asyncio

from .auth import COOKIE, check_origin, check_token
from .config import ServeConfig
from .encode import encode_frame

log = logging.getLogger("pointflow.serve")

#: Frames of one view between credit and display (jupyter_rfb's "at most two in flight").
MAX_IN_FLIGHT = 2
#: JSON messages waiting for one client (replies, picks, stats); beyond, the oldest is dropped.
MAX_TEXTS = 256
#: The page's files: nothing else is ever served.
STATIC = {"index.html": "text/html", "gestures.js": "text/javascript", "view.js": "text/javascript",
          "view.css": "text/css"}
#: Control messages the page may send on to the render stage (render/control.py).
CONTROL = ("camera", "orbit", "pan", "zoom", "fit", "follow", "style", "visible", "view_state")
PLAYBACK_KEYS = ("paused", "seek_s", "seek_fraction", "step", "rate", "loop", "hold")


class _OneLine(logging.Filter):
    """aiohttp's own error logs (a client that vanished mid-request) become one counted
    line without a traceback: no traceback reaches the user, and a hostile client cannot
    flood the log (the first 10, then every 1000th)."""

    def __init__(self, extra: dict):
        super().__init__()
        self.extra = extra

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < logging.WARNING:
            return True
        _count(self.extra, "server_errors")
        n = self.extra["server_errors"]
        if record.exc_info and record.exc_info[1] is not None:
            e = record.exc_info[1]
            record.msg, record.args = f"{record.getMessage()}: {type(e).__name__}: {e} ({n} so far)", ()
            record.exc_info, record.exc_text = None, None
        return n <= 10 or n % 1000 == 0


class BadMessage(ValueError):
    """A client message that is not one of the page's (closes that client, counted)."""


@dataclass
class ViewClient:
    view: str
    ws: Any
    width: int
    height: int
    #: Frames render may still send (credit given, not yet used).
    granted: int = 0
    #: Frames received from render and not yet acked by the page (encoding, queued, sent).
    in_flight: int = 0
    #: Frames written to the client's socket and not yet acked: only these can be acked (a
    #: client that acks without reading gets no more frames once its socket is full).
    unacked: int = 0
    queue: collections.deque = field(default_factory=collections.deque)
    #: JSON messages (replies, picks, stats) waiting for the writer, sent before frames.
    texts: collections.deque = field(default_factory=collections.deque)
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    last_sent_seq: int = -1
    #: token bucket for the client's messages
    tokens: float = 0.0
    t_tokens: float = field(default_factory=time.monotonic)
    frames_sent: int = 0
    bytes_sent: int = 0
    dropped: int = 0
    encode_ms: collections.deque = field(default_factory=lambda: collections.deque(maxlen=60))
    sizes: collections.deque = field(default_factory=lambda: collections.deque(maxlen=60))
    sent_t: collections.deque = field(default_factory=lambda: collections.deque(maxlen=120))
    closed: bool = False
    #: A playback request of this client is waiting for the sources (one at a time).
    playback_busy: bool = False


def _count(c: dict, key: str, n: int = 1) -> None:
    c[key] = c.get(key, 0) + n


class ViewServer:
    def __init__(self, sc: ServeConfig, *, views_endpoint: str, playback_endpoints: dict[str, str], token: str,
                 zctx: zmq.Context, counters=None, spans=None, sources: Optional[list[str]] = None,
                 color_by: Optional[list[str]] = None, colormaps: Optional[list[str]] = None):
        self.sc = sc
        self.token = token
        self.views_endpoint = views_endpoint
        self.playback_endpoints = playback_endpoints
        self.sources = sources or []
        self.color_by = color_by or ["z", "ingest_time", "none"]
        self.colormaps = colormaps or ["turbo"]
        self.counters = counters
        self.spans = spans
        self.extra: dict[str, Any] = counters.extra if counters is not None else {}
        for k in ("clients", "clients_total", "refused_token", "refused_origin", "refused_full", "bad_messages",
                  "rate_limited", "send_timeouts", "frames_in", "frames_sent", "dropped_frames", "bytes_sent",
                  "encode_errors", "control_sent", "control_dropped", "render_errors", "clients_gone",
                  "client_errors", "server_errors", "bogus_acks", "dropped_messages"):
            self.extra.setdefault(k, 0)
        self._zctx_sync = zctx  # the shadow does not own it: keep it alive
        self.zctx = zmq.asyncio.Context.shadow(zctx.underlying)
        self.clients: dict[str, ViewClient] = {}
        self.pool = ThreadPoolExecutor(max_workers=sc.encode_threads, thread_name_prefix="pointflow-encode")
        self.render_stats: dict[str, Any] = {}
        self.url = ""
        self._tasks: list[asyncio.Task] = []
        self._runner = None
        self._dealer = None
        self._tls = sc.tls is not None
        self._enc_ms_all: collections.deque = collections.deque(maxlen=200)
        self._bytes = {"jpeg": collections.deque(maxlen=200), "png": collections.deque(maxlen=200)}

    # ------------------------------------------------------------------ start / stop
    async def start(self) -> str:
        from aiohttp import web

        self._filter = _OneLine(self.extra)
        for name in ("aiohttp.server", "aiohttp.web", "aiohttp.websocket", "aiohttp.internal"):
            logging.getLogger(name).addFilter(self._filter)
        self._dealer = self.zctx.socket(zmq.DEALER)
        self._dealer.setsockopt(zmq.LINGER, 0)
        self._dealer.setsockopt(zmq.SNDHWM, 1000)
        self._dealer.setsockopt(zmq.RCVHWM, 64)  # frames are big: render's sends beyond this are dropped there
        self._dealer.connect(self.views_endpoint)
        app = web.Application(client_max_size=self.sc.limits.max_message_bytes)
        app.router.add_get("/", self._index)
        app.router.add_get("/ws", self._ws)
        app.router.add_get("/{name}", self._static)
        self._runner = web.AppRunner(app, access_log=None, handle_signals=False)
        await self._runner.setup()
        ctx = None
        if self.sc.tls is not None:
            ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
            ctx.load_cert_chain(self.sc.tls.cert, self.sc.tls.key)
        site = web.TCPSite(self._runner, self.sc.host, self.sc.port, ssl_context=ctx, reuse_address=True)
        await site.start()
        port = site._server.sockets[0].getsockname()[1]  # the real port when 0 was asked for
        host = self.sc.host if self.sc.host not in ("0.0.0.0", "::", "") else "127.0.0.1"
        host = f"[{host}]" if ":" in host else host
        self.url = f"{'https' if ctx else 'http'}://{host}:{port}/?token={self.token}"
        self.port = port
        self._tasks.append(asyncio.ensure_future(self._from_render()))
        self._tasks.append(asyncio.ensure_future(self._keepalive()))
        return self.url

    async def stop(self) -> None:
        for c in list(self.clients.values()):
            await self._drop_client(c, 1001, "the pipeline is stopping")
        for t in self._tasks:
            t.cancel()
        if self._runner is not None:
            await self._runner.cleanup()
        self.pool.shutdown(wait=True, cancel_futures=True)
        if self._dealer is not None:
            self._dealer.close(0)

    def _warn(self, text: str, n: int) -> None:
        """A hostile client must not flood the log: the first 10 of a kind, then every 1000th."""
        if n <= 10 or n % 1000 == 0:
            log.warning("%s", text)

    # ------------------------------------------------------------------ HTTP
    def _refuse(self, key: str, status: int, reason: str):
        from aiohttp import web

        _count(self.extra, key)
        self._warn(f"refused a client ({self.extra[key]} so far): {reason}", self.extra[key])
        return web.Response(status=status, text=f"pointflow view: {reason}\n")

    def _auth(self, request) -> Optional[str]:
        return check_token(request.query.get("token"), request.cookies.get(COOKIE), self.token)

    async def _index(self, request):
        from aiohttp import web

        why = self._auth(request)
        if why is not None:
            return self._refuse("refused_token", 403, why)
        if "token" in request.query:  # the token leaves the URL (history, screenshots): a cookie from now on
            resp = web.HTTPSeeOther("/")
            resp.set_cookie(COOKIE, self.token, httponly=True, samesite="Strict", secure=self._tls, path="/")
            raise resp
        return self._file("index.html")

    async def _static(self, request):
        name = request.match_info["name"]
        if name not in STATIC:
            from aiohttp import web

            return web.Response(status=404, text="pointflow view: not found\n")
        why = self._auth(request)
        if why is not None:
            return self._refuse("refused_token", 403, why)
        return self._file(name)

    def _file(self, name: str):
        from aiohttp import web

        body = resource_files("pointflow.serve").joinpath("static", name).read_bytes()
        return web.Response(body=body, content_type=STATIC[name],
                            headers={"Cache-Control": "no-store", "X-Content-Type-Options": "nosniff",
                                     "Content-Security-Policy": "default-src 'self'; img-src 'self' blob:; "
                                                                "connect-src 'self'; frame-ancestors 'none'"})

    # ------------------------------------------------------------------ WebSocket
    async def _ws(self, request):
        from aiohttp import WSMsgType, web

        why = self._auth(request)
        if why is not None:
            return self._refuse("refused_token", 403, why)
        why = check_origin(request.headers.get("Origin"), request.host, "https" if self._tls else "http",
                           self.sc.allowed_origins)
        if why is not None:
            return self._refuse("refused_origin", 403, why)
        lim = self.sc.limits
        if len(self.clients) >= lim.max_clients:
            return self._refuse("refused_full", 503, f"{lim.max_clients} clients already (serve.limits.max_clients)")
        ws = web.WebSocketResponse(max_msg_size=lim.max_message_bytes, compress=False, heartbeat=20.0,
                                   timeout=lim.send_timeout_s)
        sock = request.transport.get_extra_info("socket") if request.transport is not None else None
        if sock is not None:  # bounded: a client that stops reading holds at most this much
            try:
                sock.setsockopt(socketlib.SOL_SOCKET, socketlib.SO_SNDBUF, lim.socket_buffer_bytes)
            except OSError:
                pass
        try:
            await ws.prepare(request)
        except (ConnectionError, asyncio.TimeoutError):  # it left during the handshake
            _count(self.extra, "clients_gone")
            return web.Response(status=400, text="gone\n")  # aiohttp drops it quietly (the peer is gone)
        view = f"w{self.extra['clients_total']}-{secrets.token_hex(4)}"
        c = ViewClient(view, ws, self.sc.width, self.sc.height, tokens=lim.max_messages_per_s * 2)
        self.clients[view] = c
        _count(self.extra, "clients_total")
        self.extra["clients"] = len(self.clients)
        writer = asyncio.ensure_future(self._writer(c))
        reason = ""
        try:
            self._to_render(view, "open", width=c.width, height=c.height)
            self._send_json(c, {"type": "hello", "view": view, "sources": self.sources,
                                "replays": sorted(self.playback_endpoints), "max_in_flight": MAX_IN_FLIGHT,
                                "color_by": self.color_by, "colormaps": self.colormaps})
            async for msg in ws:
                if msg.type == WSMsgType.TEXT:
                    try:
                        await self._client_message(c, msg.data)
                    except BadMessage as exc:
                        _count(self.extra, "bad_messages")
                        reason = f"bad message: {exc}"
                        await ws.close(code=1008, message=str(exc)[:120].encode())
                        break
                elif msg.type == WSMsgType.BINARY:
                    _count(self.extra, "bad_messages")
                    reason = "bad message: binary messages are not taken"
                    await ws.close(code=1003, message=b"binary messages are not taken")
                    break
                elif msg.type == WSMsgType.ERROR:  # too big (aiohttp closes it with 1009)
                    _count(self.extra, "bad_messages")
                    reason = f"bad message: {ws.exception()}"
                    break
        except (ConnectionError, asyncio.TimeoutError):  # the client went away mid-message
            _count(self.extra, "clients_gone")
        except Exception as exc:  # noqa: BLE001 - one client's fault never reaches the others
            _count(self.extra, "client_errors")
            reason = f"{type(exc).__name__}: {exc}"
        finally:
            writer.cancel()
            if reason:
                self._warn(f"client {view} closed ({self.extra['bad_messages']} bad so far): {reason}",
                           self.extra["bad_messages"])
            await self._drop_client(c, 1000, "")
        return ws

    async def _drop_client(self, c: ViewClient, code: int, why: str) -> None:
        if c.closed:
            return
        c.closed = True
        self.clients.pop(c.view, None)
        self.extra["clients"] = len(self.clients)
        self._to_render(c.view, "close")
        c.wake.set()
        if not c.ws.closed:
            try:
                await asyncio.wait_for(c.ws.close(code=code, message=why.encode()), 2.0)
            except (asyncio.TimeoutError, ConnectionError, RuntimeError):
                pass

    def _limit_rate(self, c: ViewClient) -> None:
        now = time.monotonic()
        r = self.sc.limits.max_messages_per_s
        c.tokens = min(2 * r, c.tokens + (now - c.t_tokens) * r)
        c.t_tokens = now
        if c.tokens < 1:
            _count(self.extra, "rate_limited")
            raise BadMessage(f"more than {r:g} messages/s (serve.limits.max_messages_per_s)")
        c.tokens -= 1

    async def _client_message(self, c: ViewClient, text: str) -> None:
        self._limit_rate(c)
        try:
            msg = json.loads(text)
        except ValueError:
            raise BadMessage("not JSON") from None
        if not isinstance(msg, dict) or not isinstance(msg.get("cmd"), str):
            raise BadMessage("expected a JSON object with 'cmd'")
        cmd = msg.pop("cmd")
        req = msg.get("req")
        if req is not None and (isinstance(req, bool) or not isinstance(req, int)):
            raise BadMessage("'req' must be an integer")
        if cmd == "ack":  # the page has shown a frame: it may take another
            if c.unacked > 0:
                c.unacked -= 1
                c.in_flight = max(0, c.in_flight - 1)
                self._grant(c)
            else:
                _count(self.extra, "bogus_acks")
        elif cmd == "resize":
            w, h = msg.get("width"), msg.get("height")
            mx = self.sc.limits.max_view_px
            if not all(isinstance(v, int) and not isinstance(v, bool) and 16 <= v <= mx for v in (w, h)):
                raise BadMessage(f"resize: width and height must be whole numbers in 16..{mx}")
            if (w, h) != (c.width, c.height):
                c.width, c.height = w, h
                self._to_render(c.view, "resize", width=w, height=h)
            self._grant(c)
        elif cmd in CONTROL:
            self._to_render(c.view, cmd, **msg)
        elif cmd == "pick":
            x, y = msg.get("x"), msg.get("y")
            if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (x, y)):
                raise BadMessage("pick: x and y must be numbers (pixels of the view)")
            self._to_render(c.view, "pick", x=float(x), y=float(y), req=req)
        elif cmd == "playback":
            if c.playback_busy:  # one at a time per client: no pile of sockets waiting on an ended replay
                self._send_json(c, {"type": "error", "req": req, "key": "playback",
                                    "error": "the previous playback request is still waiting for the sources"})
            else:
                c.playback_busy = True
                asyncio.ensure_future(self._playback(c, msg))
        else:
            raise BadMessage(f"unknown cmd {cmd[:40]!r}")

    def _grant(self, c: ViewClient, again: bool = False) -> None:
        """Tell render how many frames this view may take now (absolute: render sets its
        credit to ``n``): two less the frames not yet shown by the page."""
        n = max(0, MAX_IN_FLIGHT - c.in_flight)
        if (n != c.granted or again) and not c.closed:
            c.granted = n
            self._to_render(c.view, "credit", n=n)

    def _to_render(self, view: str, cmd: str, **args) -> None:
        msg = {"view": view, "cmd": cmd, **args}
        try:
            self._dealer.send(json.dumps(msg).encode(), zmq.NOBLOCK)
            _count(self.extra, "control_sent")
        except zmq.Again:
            _count(self.extra, "control_dropped")

    def _send_json(self, c: ViewClient, msg: dict) -> None:
        """Queue a JSON message for the client's writer: never waits, so one slow client
        cannot hold up the others (a bounded queue; beyond it the oldest goes, counted)."""
        if c.closed:
            return
        if len(c.texts) >= MAX_TEXTS:
            c.texts.popleft()
            _count(self.extra, "dropped_messages")
        c.texts.append(json.dumps(msg))
        c.wake.set()

    # ------------------------------------------------------------------ playback (the timeline)
    async def _playback(self, c: ViewClient, msg: dict) -> None:
        try:
            await self._playback_request(c, msg)
        finally:
            c.playback_busy = False

    async def _playback_request(self, c: ViewClient, msg: dict) -> None:
        req = msg.pop("req", None)
        source = msg.pop("source", None)
        bad = sorted(set(msg) - set(PLAYBACK_KEYS))
        if bad:
            self._send_json(c, {"type": "error", "req": req, "key": f"playback.{bad[0]}",
                                "error": f"unknown argument; playback takes {', '.join(PLAYBACK_KEYS)}"})
            return
        targets = {n: e for n, e in self.playback_endpoints.items() if source is None or n == source}
        if not targets:
            self._send_json(c, {"type": "error", "req": req, "key": "playback.source",
                                "error": "no replaying source" + (f" named {source!r}" if source else "")})
            return
        out: dict[str, Any] = {}
        for name, ep in targets.items():
            sock = self.zctx.socket(zmq.REQ)
            sock.setsockopt(zmq.LINGER, 0)
            try:
                sock.connect(ep)
                await sock.send_string(json.dumps({"cmd": "playback", **msg}))
                if await sock.poll(2000):
                    out[name] = json.loads(await sock.recv())
                else:
                    out[name] = {"error": "no answer (the replay has ended or is restarting)", "key": "source"}
            finally:
                sock.close(0)
        self._send_json(c, {"type": "playback", "req": req, "sources": out})

    # ------------------------------------------------------------------ from render
    async def _from_render(self) -> None:
        while True:
            try:
                parts = await self._dealer.recv_multipart(copy=False)
            except asyncio.CancelledError:
                raise
            except zmq.ZMQError:
                return
            try:
                head = json.loads(bytes(parts[0].buffer))
            except ValueError:
                _count(self.extra, "render_errors")
                continue
            kind = head.get("type")
            if kind == "stats":
                self.render_stats = head
                continue
            c = self.clients.get(head.get("view", ""))
            if c is None or c.closed:
                continue
            if kind == "frame" and len(parts) >= 2:
                _count(self.extra, "frames_in")
                c.granted = max(0, c.granted - 1)
                c.in_flight += 1
                asyncio.ensure_future(self._encode(c, head, parts[1]))
            elif kind == "error" and head.get("key") == "view" and "unknown view" in str(head.get("error")):
                # the render stage restarted and lost the view: open it again
                self._to_render(c.view, "open", width=c.width, height=c.height)
                c.in_flight = 0
                self._grant(c, again=True)
            else:
                self._send_json(c, head)

    async def _encode(self, c: ViewClient, head: dict, frame) -> None:
        loop = asyncio.get_running_loop()
        t0 = time.monotonic_ns()
        try:
            enc = await loop.run_in_executor(self.pool, encode_frame, frame.buffer, int(head["width"]),
                                             int(head["height"]), bool(head.get("moving")), self.sc.jpeg_quality)
        except Exception as exc:  # noqa: BLE001 - one bad frame is counted, the view goes on
            _count(self.extra, "encode_errors")
            log.warning("a frame of view %s could not be encoded: %s", c.view, exc)
            c.in_flight = max(0, c.in_flight - 1)
            self._grant(c)
            return
        t1 = time.monotonic_ns()
        c.encode_ms.append(enc.encode_ms)
        self._enc_ms_all.append(enc.encode_ms)
        self._bytes["jpeg" if enc.mime == "image/jpeg" else "png"].append(len(enc.data))
        seq = int(head.get("seq", 0))
        if self.spans is not None:
            self.spans.record((hash(c.view) << 20) ^ seq or 1, "view_encode", t0, t1, int(head.get("points") or 0))
        if c.closed:
            return
        if seq <= c.last_sent_seq:  # an older frame finished after a newer one
            self._dropped(c)
            return
        hdr = {k: head.get(k) for k in ("seq", "width", "height", "moving", "version", "points", "frame_ms")}
        hdr.update(type="frame", mime=enc.mime, bytes=len(enc.data), encode_ms=round(enc.encode_ms, 2))
        hb = json.dumps(hdr).encode()
        c.queue.append((seq, struct.pack(">I", len(hb)) + hb + enc.data))
        while len(c.queue) > self.sc.limits.queue_frames:
            c.queue.popleft()
            self._dropped(c)
        c.wake.set()

    def _dropped(self, c: ViewClient) -> None:
        c.dropped += 1
        _count(self.extra, "dropped_frames")
        if self.counters is not None:
            self.counters.drop("client_queue", 1)
        c.in_flight = max(0, c.in_flight - 1)
        self._grant(c)

    async def _writer(self, c: ViewClient) -> None:
        """Sends the client's queued messages and frames (messages first); a send stuck past
        ``send_timeout_s`` (a client that never reads) closes that client only."""
        while not c.closed:
            await c.wake.wait()
            c.wake.clear()
            while (c.texts or c.queue) and not c.closed:
                text = c.texts.popleft() if c.texts else None
                if text is None:
                    seq, data = c.queue.popleft()
                try:
                    send = c.ws.send_str(text) if text is not None else c.ws.send_bytes(data)
                    await asyncio.wait_for(send, self.sc.limits.send_timeout_s)
                except asyncio.TimeoutError:
                    _count(self.extra, "send_timeouts")
                    self._warn(f"client {c.view} closed: it took nothing for {self.sc.limits.send_timeout_s:g} s "
                               f"({self.extra['send_timeouts']} so far)", self.extra["send_timeouts"])
                    asyncio.ensure_future(self._drop_client(c, 1008, "too slow"))
                    return
                except (ConnectionError, RuntimeError):
                    return
                if text is not None:
                    continue
                c.last_sent_seq = seq
                c.unacked += 1
                c.frames_sent += 1
                c.bytes_sent += len(data)
                c.sizes.append(len(data))
                c.sent_t.append(time.monotonic())
                _count(self.extra, "frames_sent")
                _count(self.extra, "bytes_sent", len(data))

    # ------------------------------------------------------------------ stats
    async def _keepalive(self) -> None:
        """Once a second: the stats line to each page; credit topped up (a lost credit
        message must not stall a view)."""
        while True:
            await asyncio.sleep(1.0)
            self.update_stats()
            rs = self.render_stats
            for c in list(self.clients.values()):
                if c.in_flight == 0:  # nothing on its way: say the credit again (a lost one must not stall)
                    self._grant(c, again=True)
                self._send_json(c, {"type": "stats", "points": rs.get("points"), "fps": rs.get("fps"),
                                          "sources": rs.get("sources", self.sources),
                                          "view": self.view_stats(c), "clients": len(self.clients)})

    def view_stats(self, c: ViewClient) -> dict:
        now = time.monotonic()
        recent = [t for t in c.sent_t if now - t <= 2.0]
        return {"fps": round(len(recent) / 2.0, 1), "frames": c.frames_sent, "drops": c.dropped,
                "bytes_per_frame": int(sum(c.sizes) / len(c.sizes)) if c.sizes else 0,
                "encode_ms": round(sum(c.encode_ms) / len(c.encode_ms), 2) if c.encode_ms else 0.0}

    def update_stats(self) -> None:
        e = self.extra
        e["clients"] = len(self.clients)
        e["encode_ms_mean"] = round(sum(self._enc_ms_all) / len(self._enc_ms_all), 3) if self._enc_ms_all else 0.0
        for k, d in self._bytes.items():
            e[f"{k}_bytes_mean"] = int(sum(d) / len(d)) if d else 0
        e["views"] = {c.view: self.view_stats(c) for c in self.clients.values()}
        e["url"] = self.url.split("?")[0]
        e["port"] = getattr(self, "port", 0)
