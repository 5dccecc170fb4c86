"""CURVE on a link socket, the ZAP authenticator of the binding end, and what the link's
socket monitor saw (handshakes, refusals, disconnects, reconnects).

The binding end runs :class:`zmq.auth.thread.ThreadAuthenticator` (ZeroMQ's ZAP handler,
in a thread of the same process, as ZAP requires). It accepts a client key only if a
``.key`` file in the authorized folder holds it; the folder is read again on every
handshake, so adding or removing a key file takes effect for the next connection. A
refused client gets nothing; the refusal is logged and counted (``refused_handshakes``).

The connecting end sees the same refusal in its own monitor (``HANDSHAKE_FAILED_AUTH``: the
server's ZAP handler said no, ZMTP's ERROR command) and says so: that the server refused
this end's key, and what to do (``refused_by_server``; ZeroMQ does not reconnect after
such a refusal); a handshake that fails otherwise
(``HANDSHAKE_FAILED_PROTOCOL``/``NO_DETAIL``: most often a ``curve_server_key`` that is not
the server's) is logged with that hint. Repeats are logged at most every 5 s, all counted.
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Any

import zmq
from zmq.auth.thread import ThreadAuthenticator
from zmq.utils.monitor import recv_monitor_message

from .keys import KeyFileError, authorized_keys, load_public, load_secret
from .options import LinkOptions

_EVENTS = (zmq.EVENT_CONNECTED | zmq.EVENT_ACCEPTED | zmq.EVENT_DISCONNECTED | zmq.EVENT_HANDSHAKE_SUCCEEDED
           | zmq.EVENT_HANDSHAKE_FAILED_AUTH | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
           | zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL)


class _KeyFolder:
    """ZAP credentials callback: the folder's keys, read per handshake; counts refusals."""

    def __init__(self, folder: str, log: logging.Logger):
        self.folder = folder
        self.log = log
        self.refused_keys = 0
        self._lock = threading.Lock()

    def callback(self, domain: str, key: bytes) -> bool:
        try:
            ok = key in authorized_keys(self.folder)
        except KeyFileError as exc:
            self.log.error("cannot read authorized keys: %s", exc)
            ok = False
        if not ok:
            with self._lock:
                self.refused_keys += 1
            self.log.warning("refused a CURVE handshake: client key %s is not in %s",
                             key.decode("ascii", "replace"), self.folder)
        return ok


class LinkSecurity:
    """Configure one link socket (CURVE, heartbeats, reconnect) and watch it.

    Call :meth:`apply` before ``bind``/``connect``, :meth:`poll` regularly (counters),
    :meth:`close` at the end."""

    def __init__(self, ctx: zmq.Context, opts: LinkOptions, bind: bool, log: logging.Logger,
                 reconnect_initial_s: float = 0.1, reconnect_max_s: float = 5.0, fatal_refusal: bool = False):
        """``fatal_refusal``: the caller raises :attr:`refusal` as its error (the zmq source),
        so it is not also logged here (an error is said once). :attr:`expected_leave`: a
        callable, true when a peer's disconnect follows its sender's own stop (its final sync
        came): said at info, not warned of."""
        self.ctx = ctx
        self.fatal_refusal = fatal_refusal
        self.expected_leave = None
        self.o = opts
        self.bind = bind
        self.log = log
        self.reconnect = (reconnect_initial_s, reconnect_max_s)
        self.auth: ThreadAuthenticator | None = None
        self._keys: _KeyFolder | None = None
        self._mon: Any = None
        self._sock: Any = None
        self.counters: dict[str, int] = {"connects": 0, "reconnects": 0, "disconnects": 0, "handshakes": 0,
                                         "refused_handshakes": 0, "peers": 0}
        if not bind:
            self.counters["refused_by_server"] = 0
        self._warned_plain = False
        self.refusal = ""
        #: endpoints whose last handshake failed: their disconnect is that failure, not a peer leaving
        self._failed: dict[str, int] = {}
        self._last_log: dict[str, float] = {}

    def _warn_every(self, what: str, msg: str, *args) -> None:
        """Log ``msg`` at most every 5 s per ``what`` (a refused client retries many times a second)."""
        now = time.monotonic()
        if now - self._last_log.get(what, -1e9) >= 5.0:
            self._last_log[what] = now
            self.log.warning(msg, *args)

    @property
    def curve(self) -> bool:
        return bool(self.o.curve_secret_key)

    def apply(self, sock: zmq.Socket) -> None:
        o = self.o
        if o.heartbeat_ivl_s:
            sock.setsockopt(zmq.HEARTBEAT_IVL, int(o.heartbeat_ivl_s * 1000))
            sock.setsockopt(zmq.HEARTBEAT_TIMEOUT, int(o.heartbeat_timeout_s * 1000))
            sock.setsockopt(zmq.HEARTBEAT_TTL, int(o.heartbeat_ttl_s * 1000))
        sock.setsockopt(zmq.RECONNECT_IVL, int(self.reconnect[0] * 1000))
        sock.setsockopt(zmq.RECONNECT_IVL_MAX, int(self.reconnect[1] * 1000))
        if self.curve:
            public, secret = load_secret(o.curve_secret_key)
            sock.curve_secretkey = secret
            sock.curve_publickey = public
            if self.bind:
                self._keys = _KeyFolder(o.curve_authorized_keys, self.log)
                self.auth = ThreadAuthenticator(self.ctx, log=logging.getLogger("pointflow.zap"))
                self.auth.start()
                self.auth.configure_curve_callback(domain="*", credentials_provider=self._keys)
                sock.curve_server = True
            else:
                sock.curve_serverkey = load_public(o.curve_server_key)
        self._sock = sock
        self._mon = sock.get_monitor_socket(_EVENTS)

    def poll(self) -> None:
        """Read the monitor's events into :attr:`counters`."""
        if self._mon is None:
            return
        c = self.counters
        while True:
            try:
                ev = recv_monitor_message(self._mon, zmq.NOBLOCK)
            except zmq.Again:
                break
            e = ev["event"]
            where = ev.get("endpoint", b"").decode(errors="replace")
            if e in (zmq.EVENT_CONNECTED, zmq.EVENT_ACCEPTED):
                if c["connects"]:
                    c["reconnects"] += 1
                c["connects"] += 1
            elif e == zmq.EVENT_HANDSHAKE_SUCCEEDED:
                c["handshakes"] += 1
                c["peers"] += 1
            elif e == zmq.EVENT_DISCONNECTED:
                c["disconnects"] += 1
                if self._failed.get(where):  # the end of a refused handshake: already said
                    self._failed[where] -= 1
                    continue
                c["peers"] = max(0, c["peers"] - 1)
                if self.expected_leave is not None and self.expected_leave():
                    self.log.info("link peer left on %s after its sender stopped; ZeroMQ reconnects if it "
                                  "comes back", where)
                else:
                    self.log.warning("link peer went away on %s; ZeroMQ reconnects", where)
            elif e in (zmq.EVENT_HANDSHAKE_FAILED_AUTH, zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL,
                       zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL):
                c["refused_handshakes"] += 1
                self._failed[where] = self._failed.get(where, 0) + 1
                if self.bind:
                    kind = {zmq.EVENT_HANDSHAKE_FAILED_AUTH: "authentication refused",
                            zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL: "protocol or key error"}.get(e, "failed")
                    self._warn_every(f"srv{e}", "link handshake %s (%s, code %s; %d refused so far)", kind, where,
                                     ev.get("value"), c["refused_handshakes"])
                elif e == zmq.EVENT_HANDSHAKE_FAILED_AUTH:
                    c["refused_by_server"] += 1
                    #: the last refusal, as logged: shown in the sender's stats (pointflow.connect raises it)
                    self.refusal = ("the server at %s refused this end's CURVE handshake (status %s; %d "
                                    "refused so far): its curve_authorized_keys folder does not hold this end's "
                                    "public key (the NAME.key of curve_secret_key %s); ZeroMQ does not retry a "
                                    "refused handshake: add the key there, then restart this end") % (
                        where, ev.get("value"), c["refused_handshakes"], self.o.curve_secret_key)
                    if not self.fatal_refusal:
                        self._warn_every("auth", "%s", self.refusal)
                else:
                    self._warn_every(f"cli{e}", "CURVE handshake with the server at %s failed (code %s; %d so far): "
                                     "is curve_server_key (%s) the binding end's public key? ZeroMQ retries",
                                     where, ev.get("value"), c["refused_handshakes"], self.o.curve_server_key or "unset")
        if self._keys is not None:
            c["refused_keys"] = self._keys.refused_keys

    def close(self) -> None:
        if self._sock is not None and self._mon is not None:
            try:
                self._sock.disable_monitor()
            except zmq.ZMQError:
                pass
        if self._mon is not None:
            self._mon.close(linger=0)
            self._mon = None
        if self.auth is not None:
            self.auth.stop()
            self.auth = None
