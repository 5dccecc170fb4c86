"""``zmq``: receive chunks from a ZeroMQ PUB (as SUB) or PUSH (as PULL) peer.

Messages are the binary wire format (:mod:`pointflow.wire`, multipart) or one-frame JSON
chunks. With ``topic_frame: true`` the first frame of each message is a topic (as many
publishers send) and is skipped. The socket connects by default (ZeroMQ then reconnects
by itself, with ``reconnect_initial_s`` doubling up to ``reconnect_max_s``); a socket
monitor counts disconnects and reconnects for the stats. ``bind: true`` binds instead.
"""
from __future__ import annotations

import dataclasses
import logging
from typing import Any, Iterator, Literal, Optional

import zmq
from zmq.utils.monitor import recv_monitor_message

from ... import wire
from ...chunk import PointChunk
from ...typed import ConfigError
from ..jsonchunk import parse_json_chunk
from ._backoff import NetworkOptions
from .base import Transport

log = logging.getLogger("pointflow.transport.zmq")


@dataclasses.dataclass
class ZmqOptions(NetworkOptions):
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

    def __init__(self, options: dict[str, Any], source_id: str):
        super().__init__(options, source_id)
        self.o = ZmqOptions(**options)
        self.counters = {"messages": 0, "rejected": 0, "connects": 0, "disconnects": 0, "reconnects": 0}
        self._ctx: zmq.Context | None = None
        self._sock = None
        self._mon = None

    def open(self) -> None:
        o = self.o
        self._ctx = zmq.Context()
        self._sock = self._ctx.socket(zmq.SUB if o.socket == "sub" else zmq.PULL)
        self._sock.setsockopt(zmq.RCVHWM, o.receive_hwm)
        self._sock.setsockopt(zmq.LINGER, 0)
        self._sock.setsockopt(zmq.RECONNECT_IVL, int(o.reconnect_initial_s * 1000))
        self._sock.setsockopt(zmq.RECONNECT_IVL_MAX, int(o.reconnect_max_s * 1000))
        if o.socket == "sub":
            self._sock.setsockopt(zmq.SUBSCRIBE, o.topic.encode())
        self._mon = self._sock.get_monitor_socket(zmq.EVENT_CONNECTED | zmq.EVENT_DISCONNECTED | zmq.EVENT_ACCEPTED)
        try:
            (self._sock.bind if o.bind else self._sock.connect)(o.endpoint)
        except zmq.ZMQError as exc:
            raise RuntimeError(f"zmq transport: cannot {'bind' if o.bind else 'connect'} {o.endpoint}: {exc}") from None

    def _poll_monitor(self) -> None:
        while True:
            try:
                ev = recv_monitor_message(self._mon, zmq.NOBLOCK)
            except zmq.Again:
                return
            e = ev["event"]
            if e in (zmq.EVENT_CONNECTED, zmq.EVENT_ACCEPTED):
                if self.counters["connects"]:
                    self.counters["reconnects"] += 1
                self.counters["connects"] += 1
            elif e == zmq.EVENT_DISCONNECTED:
                self.counters["disconnects"] += 1
                log.warning("%s: peer at %s went away; ZeroMQ reconnects", self.source_id, self.o.endpoint)

    def parse(self, frames: list) -> PointChunk:
        if self.o.topic_frame:
            frames = frames[1:]
        if len(frames) == 1:
            return parse_json_chunk(frames[0].buffer, self.o.max_points, self.source_id)
        return wire.decode(frames, self.o.max_points)

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
                if chunk is None:
                    continue
                yield chunk
                if self.quota_reached():
                    return

    def close(self) -> None:
        if self._sock is not None and self._mon is not None:
            try:
                self._sock.disable_monitor()
            except zmq.ZMQError:
                pass
        for s in (self._mon, self._sock):
            if s is not None:
                s.close(linger=0)
        if self._sock is not None:
            self._sock = None
        if self._ctx is not None:
            self._ctx.term()
            self._ctx = None
