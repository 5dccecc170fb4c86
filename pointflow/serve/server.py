"""The view server: one page, one WebSocket per browser tab, one view per WebSocket.

Between the browser and the render stage (docs/views.md):

* to render, a zmq DEALER on ``endpoints.views`` (the render stage's ROUTER): ``open`` /
  ``close`` / ``resize`` / ``credit`` and the control messages of render/view/protocol.py, each
  ``{"view": id, "cmd": ...}``;
* from render, ``[header, RGBA]`` frames (drawn only when the view changed and has credit),
  replies, picks, errors and stats;
* to the browser, each frame encoded in a thread pool (JPEG while moving, PNG when still) as
  one binary message: a 4-byte big-endian header length, the JSON header, the image;
  replies, picks, stats and errors as JSON text messages.

Flow: a view has at most :data:`~pointflow.render.view.protocol.MAX_CREDIT` frames between "credit given to render" and
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
import fcntl
import json
import logging
import os
import secrets
import socket as socketlib
import ssl
import struct
import termios
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from importlib.resources import files as resource_files
from typing import Any, Optional

import zmq
import zmq.asyncio

from ..errors import Error
from ..render.view import GESTURES_JS, OVERLAY_JS
from ..render.view.client import ClientEnd
from ..render.view.encode import encode_frame
from ..render.view.protocol import COLORMAPS, COMMANDS, MAX_CREDIT, ControlError, color_by_options, number, printable
from ..render.view.legend import lut_hex
from ..render.view.adapt import Link, encode_level
from .auth import COOKIE, check_host, check_origin, check_token, cookie_name, machine_names
from .config import ServeConfig

log = logging.getLogger("pointflow.serve")

#: JSON messages waiting for one client (replies, picks, stats); beyond, the oldest is dropped.
MAX_TEXTS = 256
#: The page's files: nothing else is ever served.
STATIC = {"index.html": "text/html", "gestures.js": "text/javascript", "view.js": "text/javascript",
          "view.css": "text/css", "overlay.js": "text/javascript", "favicon.svg": "image/svg+xml"}
#: Names a browser asks for on its own, answered with one of STATIC (no 404 in its console).
ALIASES = {"favicon.ico": "favicon.svg"}
#: The page's files that live with the view protocol, shared with the notebook widget.
SHARED = {p.name: p for p in (GESTURES_JS, OVERLAY_JS)}
PLAYBACK_KEYS = ("paused", "seek_s", "seek_fraction", "step", "rate", "loop", "hold")
#: How deep a client's JSON may nest (the page's deepest is an object holding a list).
MAX_DEPTH = 4
#: WebSocket close codes (RFC 6455): the page reconnects only after 1000/1001/1006.
CLOSE_NORMAL, CLOSE_GOING_AWAY, CLOSE_POLICY, CLOSE_INTERNAL = 1000, 1001, 1008, 1011
#: The run ended (the pipeline stops its view server): the page says so and stops retrying
#: (an application code, RFC 6455 4000-4999; a view server that restarts closes with 1006).
CLOSE_RUN_ENDED = 4000


class _OneLine(logging.Filter):
    """aiohttp's own error logs (a client that vanished mid-request) become one counted
    line without a traceback: no traceback reaches the user, and a hostile client cannot
    flood the log (the first 10, then every 1000th)."""

    def __init__(self, extra: dict, token: str = ""):
        super().__init__()
        self.extra = extra
        self.token = token

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < logging.WARNING:
            return True
        _count(self.extra, "server_errors")
        n = self.extra["server_errors"]
        text = record.getMessage()
        if record.exc_info and record.exc_info[1] is not None:
            e = record.exc_info[1]
            # the web library's parse errors quote the client's bytes (the first 100 of a
            # line too long: a Cookie or URL with the token): only the kind and status go out
            status = getattr(e, "status", None) or getattr(e, "code", None)
            what = type(e).__name__ + (f" {status}" if isinstance(status, int) else "")
            text = f"{text}: {what}" + ("" if getattr(e, "message", None) is not None or getattr(e, "headers", None)
                                        is not None else f": {e}")
        record.msg, record.args = f"{printable(redact(text, self.token), 300)} ({n} so far)", ()
        record.exc_info, record.exc_text = None, None
        return n <= 10 or n % 1000 == 0


def redact(text: str, token: str) -> str:
    """``text`` with the token, or any 8 characters of it, replaced: nothing of the token
    reaches a log line."""
    if not token:
        return text
    for i in range(max(1, len(token) - 7)):
        while token[i:i + 8] in text:
            j = max(j for j in range(i + 8, len(token) + 1) if token[i:j] in text)  # the longest piece
            text = text.replace(token[i:j], "<token>")
    return text


class _HeaderDeadline:
    """The web library's connection factory, with a deadline: a connection that has not sent
    a whole request head within ``header_timeout_s`` (a slow or silent client, before any
    token is checked) is closed and counted ``header_timeouts``. (aiohttp's keep-alive timeout,
    an hour by default, would close it too, a second later and uncounted.)"""

    def __init__(self, server, timeout_s: float, extra: dict):
        self._server = server
        self._timeout = timeout_s
        self._extra = extra
        self._cls = None

    def __getattr__(self, name):  # everything else is the web library's server
        return getattr(self._server, name)

    def __call__(self):
        handler = self._server()
        loop = asyncio.get_running_loop()
        made = handler.connection_made
        extra, timeout = self._extra, self._timeout

        def expire(transport):
            if getattr(handler, "_request_count", 1) == 0 and not transport.is_closing():
                _count(extra, "header_timeouts")
                transport.abort()

        class _Proto(asyncio.Protocol):  # the handler, with the deadline started on connection
            def __getattr__(self, name):
                return getattr(handler, name)

            def connection_made(self, transport):
                made(transport)
                loop.call_later(timeout, expire, transport)

            def data_received(self, data):
                handler.data_received(data)

            def eof_received(self):
                return handler.eof_received()

            def connection_lost(self, exc):
                handler.connection_lost(exc)

            def pause_writing(self):
                handler.pause_writing()

            def resume_writing(self):
                handler.resume_writing()

        return _Proto()


class BadMessage(Error, ValueError):
    """A client message that is not one of the page's (closes that client, counted)."""


@dataclass
class ViewClient:
    view: str
    ws: Any
    #: the view's size, credit given, newest frame number and camera (the client end the
    #: notebook widget keeps too: render/view/client.py)
    end: ClientEnd
    #: Frames received from render and not yet acked by the page (encoding, queued, sent).
    in_flight: int = 0
    #: Frames written to the client's socket and not yet acked: only these can be acked (a
    #: client that acks without reading gets no more frames once its socket is full).
    unacked: int = 0
    #: the connection, closed outright when the client is dropped (a client that stops
    #: reading never completes a close handshake, so its socket would stay open)
    transport: Any = None
    #: its socket's descriptor (the kernel's send queue: what it has not taken yet)
    fd: int = -1
    #: the size of the last frame written; a credit check is waiting to look again
    last_bytes: int = 0
    recheck: bool = False
    #: since when the frames written have stayed in its send queue (None: it reads)
    stuck_since: Optional[float] = None
    #: frames from render being encoded now, and being written (the in-flight count's
    #: repair, _keepalive)
    encoding: int = 0
    writing: int = 0
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
    #: what its link takes: the level moving frames are sent at (render/view/adapt.py)
    link: Link = field(default_factory=Link)
    #: when each control message with a ``req`` came (monotonic ns; its reply carries it)
    req_ns: dict = field(default_factory=dict)


#: Bytes a client's socket may hold unsent (besides two frames) and still get credit.
UNSENT_BYTES = 16384


def _unsent(fd: int) -> int:
    """Bytes in the kernel's send queue of socket ``fd`` (written, not yet taken by the
    peer: TIOCOUTQ); 0 where it cannot be read."""
    if fd < 0:
        return 0
    try:
        return struct.unpack("i", fcntl.ioctl(fd, termios.TIOCOUTQ, b"\0\0\0\0"))[0]
    except OSError:
        return 0


def _count(c: dict, key: str, n: int = 1) -> None:
    c[key] = c.get(key, 0) + n


def _no_constant(name: str):
    raise BadMessage(f"{name} is not a JSON number")


def _depth(v: Any) -> int:
    """How deep ``v`` nests (without recursion: a hostile message may nest hundreds deep)."""
    deepest, todo = 0, [(v, 1)]
    while todo:
        x, d = todo.pop()
        deepest = max(deepest, d)
        if deepest > MAX_DEPTH:
            break
        if isinstance(x, dict):
            todo.extend((y, d + 1) for y in x.values())
        elif isinstance(x, list):
            todo.extend((y, d + 1) for y in x)
    return deepest


def _finite(v: Any) -> Any:
    """``v`` with every non-finite float as null (valid JSON for the page)."""
    if isinstance(v, float):
        return v if v == v and abs(v) != float("inf") else None
    if isinstance(v, dict):
        return {k: _finite(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_finite(x) for x in v]
    return v


class ViewServer:
    def __init__(self, sc: ServeConfig, *, views_endpoint: str, playback_endpoints: dict[str, str], token: str,
                 zctx: zmq.Context, counters=None, spans=None, sources: Optional[list[str]] = None,
                 color_by: Optional[list[str]] = None, colormaps: Optional[list[str]] = None, run_dir: str = ""):
        self.sc = sc
        self.token = token
        self.run_dir = run_dir or secrets.token_hex(8)
        self.cookie = COOKIE  # named for the port once listening (auth.cookie_name)
        self.views_endpoint = views_endpoint
        self.playback_endpoints = playback_endpoints
        self.sources = sources or []
        self.color_by = color_by or color_by_options([])
        self.colormaps = colormaps or ["turbo"]
        self.counters = counters
        self.spans = spans
        self.extra: dict[str, Any] = counters.extra if counters is not None else {}
        for k in ("clients", "clients_total", "refused_token", "refused_origin", "refused_full", "bad_messages",
                  "rate_limited", "send_timeouts", "frames_in", "frames_sent", "dropped_frames", "bytes_sent",
                  "encode_errors", "control_sent", "control_dropped", "render_errors", "clients_gone",
                  "client_errors", "server_errors", "bogus_acks", "dropped_messages", "refused_host",
                  "header_timeouts", "views_reopened", "credit_withheld"):
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

        self._filter = _OneLine(self.extra, self.token)
        for name in ("aiohttp.server", "aiohttp.web", "aiohttp.websocket", "aiohttp.internal", "aiohttp.access",
                     "aiohttp.client"):
            logging.getLogger(name).addFilter(self._filter)
        self._dealer = self.zctx.socket(zmq.DEALER)
        self._dealer.setsockopt(zmq.LINGER, 0)
        self._dealer.setsockopt(zmq.SNDHWM, 1000)
        self._dealer.setsockopt(zmq.RCVHWM, 64)  # frames are big: render's sends beyond this are dropped there
        self._dealer.connect(self.views_endpoint)
        host_check = web.middleware(lambda request, handler: self._host_check(request, handler))
        app = web.Application(client_max_size=self.sc.limits.max_message_bytes, middlewares=[host_check])
        app.router.add_get("/", self._index)
        app.router.add_get("/ws", self._ws)
        app.router.add_get("/{name}", self._static)
        # an idle keep-alive connection goes after header_timeout_s (aiohttp's default: an hour);
        # one that never finishes its first request head goes a little earlier, counted (_HeaderDeadline)
        self._runner = web.AppRunner(app, access_log=None, handle_signals=False,
                                     keepalive_timeout=self.sc.limits.header_timeout_s + 1.0)
        await self._runner.setup()
        self._runner._server = _HeaderDeadline(self._runner.server, self.sc.limits.header_timeout_s, self.extra)
        ctx = None
        if self.sc.tls is not None:
            ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
            ctx.load_cert_chain(self.sc.tls.cert, self.sc.tls.key)
        site = web.TCPSite(self._runner, self.sc.host, self.sc.port, ssl_context=ctx, reuse_address=True)
        await site.start()
        if self.sc.host in ("0.0.0.0", "::", ""):  # the names a Host may use, looked up once, off the loop
            await asyncio.get_running_loop().run_in_executor(None, machine_names)
        port = site._server.sockets[0].getsockname()[1]  # the real port when 0 was asked for
        host = self.sc.host if self.sc.host not in ("0.0.0.0", "::", "") else "127.0.0.1"
        host = f"[{host}]" if ":" in host else host
        self.url = f"{'https' if ctx else 'http'}://{host}:{port}/?token={self.token}"
        self.port = port
        self.cookie = cookie_name(port, self.run_dir)
        self._tasks.append(asyncio.ensure_future(self._from_render()))
        self._tasks.append(asyncio.ensure_future(self._keepalive()))
        return self.url

    async def stop(self) -> None:
        await asyncio.gather(*(self._drop_client(c, CLOSE_RUN_ENDED, "run ended")
                               for c in list(self.clients.values())))
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
            log.warning("%s", printable(redact(text, self.token), 400))

    # ------------------------------------------------------------------ HTTP
    def _refuse(self, key: str, status: int, reason: str):
        from aiohttp import web

        _count(self.extra, key)
        self._warn(f"refused a client ({self.extra[key]} so far): {reason}", self.extra[key])
        resp = web.Response(status=status, text=f"pointflow view: {printable(reason, 300)}\n")
        resp.force_close()  # a refused connection is not kept alive
        return resp

    async def _host_check(self, request, handler):
        """Every request's Host is checked before anything else (DNS rebinding)."""
        why = check_host(request.headers.get("Host"), self.sc.host, self.sc.allowed_hosts)
        if why is not None:
            return self._refuse("refused_host", 403, why)
        return await handler(request)

    def _auth(self, request) -> Optional[str]:
        return check_token(request.query.get("token"), request.cookies.get(self.cookie), self.token)

    async def _index(self, request):
        from aiohttp import web

        why = self._auth(request)
        if why is not None:
            return self._refuse("refused_token", 403, why)
        if "token" in request.query:  # the token leaves the URL (history, screenshots): a cookie from now on
            resp = web.HTTPSeeOther("/")
            resp.set_cookie(self.cookie, self.token, httponly=True, samesite="Strict", secure=self._tls, path="/")
            raise resp
        return self._file("index.html")

    async def _static(self, request):
        name = request.match_info["name"]
        name = ALIASES.get(name, name)
        if name not in STATIC:
            from aiohttp import web

            return web.Response(status=404, text="pointflow view: not found\n")
        why = self._auth(request)
        if why is not None:
            return self._refuse("refused_token", 403, why)
        return self._file(name)

    def _file(self, name: str):
        from aiohttp import web

        shared = SHARED.get(name)  # the scripts the notebook widget loads too (render/view/static)
        body = (shared.read_bytes() if shared is not None
                else resource_files("pointflow.serve").joinpath("static", name).read_bytes())
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
        fd = -1
        if sock is not None:  # bounded: a client that stops reading holds at most this much
            try:
                sock.setsockopt(socketlib.SOL_SOCKET, socketlib.SO_SNDBUF, lim.socket_buffer_bytes)
                fd = sock.fileno()
            except OSError:
                pass
        try:
            await ws.prepare(request)
        except (ConnectionError, asyncio.TimeoutError):  # it left during the handshake
            _count(self.extra, "clients_gone")
            return web.Response(status=400, text="gone\n")  # aiohttp drops it quietly (the peer is gone)
        view = f"w{self.extra['clients_total']}-{secrets.token_hex(4)}"
        c = ViewClient(view, ws, ClientEnd(self.sc.width, self.sc.height), tokens=lim.max_messages_per_s * 2,
                       transport=request.transport, fd=fd, link=Link(target_fps=self.sc.adapt_fps))
        self.clients[view] = c
        _count(self.extra, "clients_total")
        self.extra["clients"] = len(self.clients)
        writer = asyncio.ensure_future(self._writer(c))
        reason, code = "", CLOSE_NORMAL
        try:
            self._to_render(view, **c.end.open())
            self._send_json(c, {"type": "hello", "view": view, "sources": self.sources,
                                "replays": sorted(self.playback_endpoints), "max_in_flight": MAX_CREDIT,
                                "color_by": self.color_by, "colormaps": self.colormaps,
                                "luts": {n: lut_hex(n) for n in self.colormaps if n in COLORMAPS}})
            async for msg in ws:
                if msg.type == WSMsgType.TEXT:
                    try:
                        await self._client_message(c, msg.data)
                    except BadMessage as exc:
                        _count(self.extra, "bad_messages")
                        reason, code = f"bad message: {exc}", CLOSE_POLICY
                        await self._close_ws(c, CLOSE_POLICY, str(exc))
                        break
                elif msg.type == WSMsgType.BINARY:
                    _count(self.extra, "bad_messages")
                    reason, code = "bad message: binary messages are not taken", 1003
                    await self._close_ws(c, 1003, "binary messages are not taken")
                    break
                elif msg.type == WSMsgType.ERROR:  # too big (aiohttp closes it with 1009)
                    _count(self.extra, "bad_messages")
                    reason, code = f"bad message: {ws.exception()}", 1009
                    break
        except (ConnectionError, asyncio.TimeoutError):  # the client went away mid-message
            _count(self.extra, "clients_gone")
        except Exception as exc:  # noqa: BLE001 - one client's fault never reaches the others
            _count(self.extra, "client_errors")
            reason, code = f"internal error: {type(exc).__name__}: {exc}", CLOSE_INTERNAL
        finally:
            writer.cancel()
            if reason:
                n = self.extra["bad_messages"] + self.extra["client_errors"]
                self._warn(f"client {view} closed ({self.extra['bad_messages']} bad so far): {reason}", n)
            await self._drop_client(c, code, "internal error" if code == CLOSE_INTERNAL else "")
        return ws

    async def _close_ws(self, c: ViewClient, code: int, why: str) -> None:
        """Close with ``code`` and a short reason; a client that does not take the close
        frame within 2 s (it stopped reading) loses its connection outright."""
        done = c.ws.closed
        if not done:
            # not wait_for: a close stuck behind a full socket does not end when cancelled
            closing = asyncio.ensure_future(c.ws.close(code=code, message=printable(why, 120).encode()[:123]))
            closing.add_done_callback(lambda f: f.cancelled() or f.exception())  # retrieved: no warning
            await asyncio.wait({closing}, timeout=2.0)
            done = closing.done() and not closing.cancelled() and closing.exception() is None
        t = c.transport
        # a transport closed with data it cannot send (the client stopped reading) stays
        # ESTABLISHED, holding its buffers, until the kernel gives up: abort it
        if t is not None and (not done or t.get_write_buffer_size() > 0):
            t.abort()

    async def _drop_client(self, c: ViewClient, code: int, why: str) -> None:
        if c.closed:
            return
        c.closed = True
        self.clients.pop(c.view, None)
        self.extra["clients"] = len(self.clients)
        self._to_render(c.view, "close")
        c.wake.set()
        await self._close_ws(c, code, why)

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
            msg = json.loads(text, parse_constant=_no_constant)
        except (ValueError, RecursionError) as exc:  # incl. NaN/Infinity, digits past Python's limit, deep nesting
            raise BadMessage("not JSON" + (f" ({exc})" if isinstance(exc, BadMessage) else "")) from None
        if not isinstance(msg, dict) or not isinstance(msg.get("cmd"), str):
            raise BadMessage("expected a JSON object with 'cmd'")
        if _depth(msg) > MAX_DEPTH:
            raise BadMessage(f"nested deeper than {MAX_DEPTH} levels")
        if "view" in msg:  # the envelope's key: a client does not name views
            raise BadMessage("'view' is not an argument a client gives (each connection is one view)")
        cmd = msg.pop("cmd")
        req = msg.get("req")
        if req is not None and (isinstance(req, bool) or not isinstance(req, int)):
            raise BadMessage("'req' must be an integer")
        if cmd == "ack":  # the page has shown a frame: it may take another
            if c.unacked > 0:
                c.unacked -= 1
                c.in_flight = max(0, c.in_flight - 1)
                now = time.monotonic()
                c.link.acked(now)
                c.link.flight(c.in_flight >= MAX_CREDIT, now)
                self._grant(c)
            else:
                _count(self.extra, "bogus_acks")
        elif cmd == "resize":
            w, h = msg.get("width"), msg.get("height")
            mx = self.sc.limits.max_view_px
            if not all(isinstance(v, int) and not isinstance(v, bool) and 16 <= v <= mx for v in (w, h)):
                raise BadMessage(f"resize: width and height must be whole numbers in 16..{mx}")
            change = c.end.resize(w, h)
            if change is not None:
                self._to_render(c.view, **change)
            self._grant(c)
        elif cmd in COMMANDS:
            if req is not None:  # when it came: its reply says (where a drag's time goes, bench_drag.py)
                c.req_ns[req] = time.monotonic_ns()
                while len(c.req_ns) > 64:
                    c.req_ns.pop(next(iter(c.req_ns)))
            self._to_render(c.view, cmd, **msg)
        elif cmd == "pick":
            try:
                x, y = (number(msg.get(k), f"pick.{k}", -1e6, 1e6) for k in ("x", "y"))
            except ControlError as exc:
                raise BadMessage(f"{exc} (pixels of the view)") from None
            self._to_render(c.view, "pick", x=x, y=y, req=req)
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
        credit to ``n``): two less the frames not yet shown by the page, and none while the
        frames written are still in the kernel's send queue: a client that acks frames it
        never reads (a "liar") gets no more than its socket has taken."""
        if c.closed:
            return
        n = max(0, MAX_CREDIT - c.in_flight)
        withhold = False
        if n > 0 and _unsent(c.fd) <= max(2 * c.last_bytes, UNSENT_BYTES):
            c.stuck_since = None
        elif n > 0:
            withhold = True
            _count(self.extra, "credit_withheld")
            if c.stuck_since is None:
                c.stuck_since = time.monotonic()
            if not c.recheck:  # look again soon: an honest client on a slow link
                c.recheck = True
                asyncio.get_running_loop().call_later(0.05, self._recheck, c)
        msg = c.end.credit(c.in_flight, again=again, withhold=withhold)
        if msg is not None:
            self._to_render(c.view, **msg)

    def _recheck(self, c: ViewClient) -> None:
        c.recheck = False
        self._grant(c)

    def _too_slow(self, c: ViewClient) -> None:
        """A client that has taken nothing for ``send_timeout_s`` is closed (its own only)."""
        _count(self.extra, "send_timeouts")
        self._warn(f"client {c.view} closed: it took nothing for {self.sc.limits.send_timeout_s:g} s "
                   f"({self.extra['send_timeouts']} so far)", self.extra["send_timeouts"])
        asyncio.ensure_future(self._drop_client(c, CLOSE_POLICY, "too slow"))

    def _to_render(self, view: str, cmd: str, **args: Any) -> None:
        msg = {**args, "view": view, "cmd": cmd}
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
        try:
            text = json.dumps(msg, allow_nan=False)
        except ValueError:  # NaN is not JSON: the page's JSON.parse would throw the message away
            text = json.dumps(_finite(msg), allow_nan=False)
        c.texts.append(text)
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
            what = c.end.from_render(head)  # credit used, frame numbers, the camera of a reply
            if what == "frame" and len(parts) >= 2:
                _count(self.extra, "frames_in")
                c.in_flight += 1
                c.link.flight(c.in_flight >= MAX_CREDIT, time.monotonic())
                c.encoding += 1
                asyncio.ensure_future(self._encode(c, head, parts[1]))
            elif what == "gone":
                self._reopen(c)
            else:
                if kind == "reply" and head.get("req") in c.req_ns:
                    head["served_ns"] = c.req_ns.pop(head["req"])
                self._send_json(c, head)

    def _reopen(self, c: ViewClient) -> None:
        """The render stage restarted and lost the view: open it again with its size, its
        camera and a frame number past every frame already seen (else the new stage's
        frames, numbered from 1, would be taken for old ones and dropped), then give credit
        for the frames the page does not hold."""
        _count(self.extra, "views_reopened")
        self._to_render(c.view, **c.end.open(again=True, seen=c.last_sent_seq))
        self._repair_in_flight(c)
        self._grant(c, again=True)

    def _repair_in_flight(self, c: ViewClient) -> None:
        """Frames in flight are those being encoded, queued, or written and not yet acked;
        any counted beyond (lost with a dead render stage or a failed write) are forgotten,
        so a view never waits for frames that will not come."""
        real = c.encoding + len(c.queue) + c.writing + c.unacked
        if c.in_flight > real:
            c.in_flight = real

    async def _encode(self, c: ViewClient, head: dict, frame) -> None:
        try:
            await self._encode_one(c, head, frame)
        finally:
            c.encoding = max(0, c.encoding - 1)

    async def _encode_one(self, c: ViewClient, head: dict, frame) -> None:
        loop = asyncio.get_running_loop()
        t0 = time.monotonic_ns()
        w, h, moving = int(head["width"]), int(head["height"]), bool(head.get("moving"))
        level, how = c.link.choose(moving, w * h)  # smaller while moving on a slow link (render/view/adapt.py)
        try:
            enc = await loop.run_in_executor(self.pool, encode_level, frame.buffer, w, h, how, self.sc.jpeg_quality)
        except Exception as exc:  # noqa: BLE001 - one bad frame is counted, the view goes on
            _count(self.extra, "encode_errors")
            log.warning("a frame of view %s could not be encoded: %s", c.view, printable(exc))
            c.in_flight = max(0, c.in_flight - 1)
            self._grant(c)
            return
        t1 = time.monotonic_ns()
        if moving:
            c.link.encoded(level, len(enc.data), w * h)
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
        hdr = {k: head.get(k) for k in ("seq", "width", "height", "moving", "version", "points", "frame_ms", "t_ns",
                                       "camera", "legend", "follow", "units")}
        hdr.update(type="frame", mime=enc.mime, bytes=len(enc.data), encode_ms=round(enc.encode_ms, 2),
                   reduce=how.reduce, quality=0 if how.lossless else how.quality or self.sc.jpeg_quality)
        hb = json.dumps(hdr).encode()
        c.queue.append((seq, struct.pack(">I", len(hb)) + hb + enc.data, moving))
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
                    seq, data, moving = c.queue.popleft()
                    c.writing = 1
                    c.link.sent(len(data), moving, time.monotonic())  # before the await: its ack may come first
                try:
                    send = c.ws.send_str(text) if text is not None else c.ws.send_bytes(data)
                    await asyncio.wait_for(send, self.sc.limits.send_timeout_s)
                except asyncio.TimeoutError:
                    self._too_slow(c)
                    return
                except (ConnectionError, RuntimeError):
                    return
                finally:
                    c.writing = 0
                if text is not None:
                    continue
                c.last_sent_seq = seq
                c.last_bytes = len(data)
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
                # say the credit again, every second: a lost one must not stall a view, and a
                # render stage that restarted answers that the view is gone (it is opened again)
                self._repair_in_flight(c)
                self._grant(c, again=True)
                if c.stuck_since is not None and time.monotonic() - c.stuck_since > self.sc.limits.send_timeout_s:
                    self._too_slow(c)
                    continue
                self._send_json(c, {"type": "stats", "points": rs.get("points"), "fps": rs.get("fps"),
                                          "sources": rs.get("sources", self.sources),
                                          "view": self.view_stats(c), "clients": len(self.clients)})

    def view_stats(self, c: ViewClient) -> dict:
        now = time.monotonic()
        recent = [t for t in c.sent_t if now - t <= 2.0]
        return {"fps": round(len(recent) / 2.0, 1), "frames": c.frames_sent, "drops": c.dropped,
                "bytes_per_frame": int(sum(c.sizes) / len(c.sizes)) if c.sizes else 0,
                "encode_ms": round(sum(c.encode_ms) / len(c.encode_ms), 2) if c.encode_ms else 0.0,
                "link": c.link.stats(now)}

    def update_stats(self) -> None:
        e = self.extra
        e["clients"] = len(self.clients)
        e["encode_ms_mean"] = round(sum(self._enc_ms_all) / len(self._enc_ms_all), 3) if self._enc_ms_all else 0.0
        for k, d in self._bytes.items():
            e[f"{k}_bytes_mean"] = int(sum(d) / len(d)) if d else 0
        e["views"] = {c.view: self.view_stats(c) for c in self.clients.values()}
        e["url"] = self.url.split("?")[0]
        e["port"] = getattr(self, "port", 0)
        e["cookie"] = self.cookie  # the token cookie's name (not secret): per run and port
