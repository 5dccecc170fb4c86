"""``websocket``: a client of a point-streaming websocket server.

Text messages are JSON chunks (point list or columnar, see
:mod:`pointflow.ingest.jsonchunk`); binary messages are PointFlow's quantised frames (see
:mod:`pointflow.ingest.quantised`, attribute ranges from the ``attributes`` option) or, if
they start with ``{``, JSON. Malformed messages are rejected and counted, the connection
stays up. When the server goes away the client reconnects with exponential backoff
(``reconnects`` in stats).
"""
from __future__ import annotations

import dataclasses
import logging
from typing import Any, Iterator, Optional

from ...chunk import ChunkError, PointChunk
from ...typed import ConfigError
from ..jsonchunk import parse_json_chunk
from ..quantised import AttributeRange, decode_quantised
from ._backoff import Backoff, NetworkOptions
from .base import Transport

log = logging.getLogger("pointflow.transport.websocket")


@dataclasses.dataclass
class AttributeOption:
    name: str
    min: float = 0.0
    max: float = 1.0


@dataclasses.dataclass
class WebSocketOptions(NetworkOptions):
    url: str = "ws://127.0.0.1:8765"
    #: Schema of the quantised binary frames: attribute j -> channel name and range.
    attributes: list[AttributeOption] = dataclasses.field(default_factory=list)
    #: Sent once after every (re)connect, e.g. a subscription request.
    subscribe: Optional[str] = None


class WebSocketTransport(Transport):
    name = "websocket"
    options_schema = WebSocketOptions

    @classmethod
    def check_options(cls, o: WebSocketOptions, path: str, base_dir: str) -> None:
        if not o.url.startswith(("ws://", "wss://")):
            raise ConfigError(f"{path}.url", f"must start with ws:// or wss://, got {o.url!r}")
        for i, a in enumerate(o.attributes):
            if not a.max > a.min:
                raise ConfigError(f"{path}.attributes[{i}].max", f"must be greater than min ({a.min}), got {a.max}")
        for key in ("reconnect_initial_s", "reconnect_max_s", "connect_timeout_s"):
            if getattr(o, key) <= 0:
                raise ConfigError(f"{path}.{key}", "must be > 0")

    def __init__(self, options: dict[str, Any], source_id: str):
        super().__init__(options, source_id)
        o = dict(options)
        o["attributes"] = [a if isinstance(a, AttributeOption) else AttributeOption(**a) for a in o.get("attributes", [])]
        self.o = WebSocketOptions(**o)
        self.schema = [AttributeRange(a.name, a.min, a.max) for a in self.o.attributes]
        self.counters = {"connects": 0, "reconnects": 0, "messages": 0, "rejected": 0}
        self._ws = None
        self._backoff = Backoff(self.o.reconnect_initial_s, self.o.reconnect_max_s)

    def _connect(self) -> bool:
        from websockets.sync.client import connect

        kw = dict(open_timeout=self.o.connect_timeout_s, max_size=None, compression=None)
        try:
            try:  # websockets >= 16: a direct (not context-managed) connection is "legacy"
                self._ws = connect(self.o.url, legacy=True, **kw)
            except TypeError:
                self._ws = connect(self.o.url, **kw)
        except Exception as exc:  # noqa: BLE001 - refused, DNS, handshake: retry later
            if self.counters["connects"] == 0 and self._backoff.delay == self._backoff.initial:
                log.warning("%s: cannot connect to %s (%s); retrying with backoff", self.source_id, self.o.url, exc)
            self._backoff.failed()
            return False
        if self.counters["connects"]:
            self.counters["reconnects"] += 1
            log.info("%s: reconnected to %s", self.source_id, self.o.url)
        self.counters["connects"] += 1
        self._backoff.ok()
        self.on_connect()
        return True

    def on_connect(self) -> None:
        """After every (re)connect: send the ``subscribe`` option (subclasses send their own)."""
        if self.o.subscribe:
            self._ws.send(self.o.subscribe)

    def _drop_connection(self, why: str) -> None:
        log.warning("%s: connection to %s lost (%s); reconnecting", self.source_id, self.o.url, why)
        try:
            self._ws.close()
        except Exception:  # noqa: BLE001
            pass
        self._ws = None
        self._backoff.failed()

    def parse(self, msg: bytes | str) -> PointChunk:
        """One websocket message -> chunk (raises ChunkError)."""
        if isinstance(msg, str):
            return parse_json_chunk(msg, self.o.max_points, self.source_id)
        if msg[:1] == b"{":
            return parse_json_chunk(msg, self.o.max_points, self.source_id)
        chunk = decode_quantised(msg, self.schema, self.source_id)
        if chunk.n > self.o.max_points:
            raise ChunkError("too_large", f"{chunk.n} points, more than max_points {self.o.max_points}")
        return chunk

    def chunks(self) -> Iterator[Optional[PointChunk]]:
        import time
        while True:
            if self._ws is None:
                if not self._backoff.ready() or not self._connect():
                    time.sleep(0.02)
                    yield None
                    continue
            try:
                msg = self._ws.recv(timeout=0.05)
            except TimeoutError:
                yield None
                continue
            except Exception as exc:  # noqa: BLE001 - closed, reset: reconnect
                self._drop_connection(f"{type(exc).__name__}: {exc}")
                yield None
                continue
            self.counters["messages"] += 1
            chunk = self.accept(self.parse, msg)
            if chunk is None:
                continue
            yield chunk
            if isinstance(chunk, PointChunk) and self.quota_reached():  # transforms do not count
                return

    def close(self) -> None:
        if self._ws is not None:
            try:
                self._ws.close()
            except Exception:  # noqa: BLE001
                pass
            self._ws = None
