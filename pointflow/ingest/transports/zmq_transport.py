"""``zmq``: receive chunks from a ZeroMQ PUB (as SUB) or PUSH (as PULL) peer.

Messages are the binary wire format (:mod:`pointflow.wire`, multipart) or one-frame JSON
chunks. With ``topic_frame: true`` the first frame of each message is a topic (as many
publishers send) and is skipped. The socket connects by default (ZeroMQ then reconnects
by itself, with ``reconnect_initial_s`` doubling up to ``reconnect_max_s``); a socket
monitor counts disconnects and reconnects for the stats. ``bind: true`` binds instead.

The receiving end of a link from ``pointflow send`` (docs/remote.md): CURVE keys, ZeroMQ
heartbeats (:class:`pointflow.remote.options.LinkOptions`), compressed or quantised
chunks (decoded by :mod:`pointflow.wire`) and ``lost_in_transit`` per source from the
``link`` header (:mod:`pointflow.remote.transit`). A ``tcp://`` endpoint on a
non-loopback address without CURVE is refused at load unless ``insecure: true``. A
connecting end whose key the sender refuses fails the run (exit 2) with the refusal's
reason: ZeroMQ does not retry a refused handshake.
"""
from __future__ import annotations

import dataclasses
import logging
from typing import Any, Iterator, Literal, Optional

import zmq

from ... import wire
from ...chunk import PointChunk
from ...remote.options import LinkOptions, check_link_options
from ...remote.security import LinkSecurity
from ...remote.transit import TransitLedger
from ...typed import ConfigError
from ..jsonchunk import parse_json_chunk
from ._backoff import NetworkOptions
from .base import InputUnreadable, Transport

log = logging.getLogger("pointflow.transport.zmq")


@dataclasses.dataclass
class ZmqOptions(NetworkOptions, LinkOptions):
    endpoint: str = "tcp://127.0.0.1:5556"
    socket: Literal["sub", "pull"] = "sub"
    bind: bool = False
    #: SUB subscription prefix ("" = everything).
    topic: str = ""
    #: The first frame of each message is a topic to skip.
    topic_frame: bool = False
    receive_hwm: int = 1000


class ZmqTransport(Transport):
    name = "zmq"
    options_schema = ZmqOptions

    @classmethod
    def check_options(cls, o: ZmqOptions, path: str, base_dir: str) -> None:
        if not o.endpoint.startswith(("tcp://", "ipc://", "inproc://", "pgm://", "epgm://")):
            raise ConfigError(f"{path}.endpoint", f"must be a ZeroMQ endpoint (tcp://host:port, ipc://path), got {o.endpoint!r}")
        if o.receive_hwm < 1:
            raise ConfigError(f"{path}.receive_hwm", "must be >= 1")
        check_link_options(o, path, o.endpoint, o.bind, base_dir)

    def __init__(self, options: dict[str, Any], source_id: str):
        super().__init__(options, source_id)
        self.o = ZmqOptions(**options)
        self.counters = {"messages": 0, "rejected": 0, "connects": 0, "disconnects": 0, "reconnects": 0}
        self._ctx: zmq.Context | None = None
        self._sock = None
        self._link: LinkSecurity | None = None
        self.ledger = TransitLedger()

    def open(self) -> None:
        o = self.o
        self._ctx = zmq.Context()
        self._sock = self._ctx.socket(zmq.SUB if o.socket == "sub" else zmq.PULL)
        self._sock.setsockopt(zmq.RCVHWM, o.receive_hwm)
        self._sock.setsockopt(zmq.LINGER, 0)
        if o.socket == "sub":
            self._sock.setsockopt(zmq.SUBSCRIBE, o.topic.encode())
        self._link = LinkSecurity(self._ctx, o, o.bind, log, o.reconnect_initial_s, o.reconnect_max_s,
                                  fatal_refusal=True)
        # a sender that said it stopped (its final sync) then closes its end: not a peer lost
        self._link.expected_leave = lambda: bool(self.ledger.ended)
        self._link.apply(self._sock)
        try:
            (self._sock.bind if o.bind else self._sock.connect)(o.endpoint)
        except zmq.ZMQError as exc:
            raise RuntimeError(f"zmq transport: cannot {'bind' if o.bind else 'connect'} {o.endpoint}: {exc}") from None

    def _poll_monitor(self, closing: bool = False) -> None:
        if self._link is not None:
            self._link.poll()
            self.counters.update(self._link.counters)
            if self._link.refusal and not self.o.bind and not closing:
                # the sender's ZAP said no to this end's key: ZeroMQ does not connect again, so
                # nothing can arrive; the run fails, saying why (it used to run on, empty, and exit 0)
                raise InputUnreadable(f"source {self.source_id!r}: {self._link.refusal}")

    def parse(self, frames: list) -> PointChunk:
        if self.o.topic_frame:
            frames = frames[1:]
        if len(frames) == 1:
            return parse_json_chunk(frames[0].buffer, self.o.max_points, self.source_id)
        chunk, header = wire.decode_message(frames, self.o.max_points)
        link = header.get("link")
        if link is not None:
            src = chunk.source_id or self.source_id
            delivered = self.ledger.observe(src, link, chunk.n)
            self.counters.update(self.ledger.counters())
            if not delivered:  # a sync: totals only
                if src in self.ledger.ended:
                    t = self.ledger.per_source()[src]
                    log.info("%s: sender of %r stopped: sent %d, received %d, lost in transit %d point(s)%s",
                             self.source_id, src, t["sent"], t["received"], t["lost_points"], self._joined_after(t))
                return None
        return chunk

    def _joined_after(self, t: dict) -> str:
        """The stopped-sender line's note of the points sent before this source joined."""
        late = t.get("joined_after", 0)
        if not late:
            return ""
        why = ("; a pub sender's first chunks go before a subscriber is connected: send.wait_subscribers "
               "on the sender keeps them") if self.o.socket == "sub" else ""
        return f"; {late} point(s) sent before this source joined (transport_joined_after{why})"

    def chunks(self) -> Iterator[Optional[PointChunk]]:
        while True:
            self._poll_monitor()
            if not self._sock.poll(50, zmq.POLLIN):
                yield None
                continue
            for _ in range(64):
                try:
                    frames = self._sock.recv_multipart(zmq.NOBLOCK, copy=False)
                except zmq.Again:
                    break
                self.counters["messages"] += 1
                chunk = self.accept(self.parse, frames)
                if chunk is None:  # rejected (counted) or a link sync
                    continue
                yield chunk
                if self.quota_reached():
                    return

    def close(self) -> None:
        if self._link is not None:
            self._poll_monitor(closing=True)
            self._link.close()
            self._link = None
        if self._sock is not None:
            self._sock.close(linger=0)
            self._sock = None
        if self._ctx is not None:
            self._ctx.term()
            self._ctx = None
