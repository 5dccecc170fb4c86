"""``sse``: an HTTP Server-Sent Events client; each ``data:`` event is a JSON chunk.

A small HTTP/1.1 client on a plain socket (no new dependency), read with ``select`` so
``chunks()`` never blocks for more than ~50 ms: it parses the status line and headers,
de-chunks ``Transfer-Encoding: chunked`` bodies incrementally and splits events on blank
lines (multi-line ``data:`` joined with newlines, comments and ``event:``/``retry:``
fields handled as the SSE spec says). On EOF, error or a non-200 answer it reconnects
with exponential backoff, sending ``Last-Event-ID`` (``reconnects`` in stats).
"""
from __future__ import annotations

import dataclasses
import logging
import select
import socket
import ssl
import time
from typing import Any, Iterator, Optional
from urllib.parse import urlsplit

from ...chunk import PointChunk
from ...errors import Error
from ...typed import ConfigError
from ..jsonchunk import parse_json_chunk
from ._backoff import Backoff, NetworkOptions
from .base import Transport

log = logging.getLogger("pointflow.transport.sse")

#: An event larger than this is rejected (and the connection reset) instead of buffered.
MAX_EVENT_BYTES = 64 * 1024 * 1024


@dataclasses.dataclass
class SseOptions(NetworkOptions):
    url: str = "http://127.0.0.1:8080/stream"
    #: Only events of this type (``event:`` field; default type is "message"); null = all.
    event: Optional[str] = None
    headers: dict[str, str] = dataclasses.field(default_factory=dict)


class _HttpError(Error):
    pass


class SseTransport(Transport):
    name = "sse"
    options_schema = SseOptions

    @classmethod
    def check_options(cls, o: SseOptions, path: str, base_dir: str) -> None:
        u = urlsplit(o.url)
        if u.scheme not in ("http", "https") or not u.hostname:
            raise ConfigError(f"{path}.url", f"must be an http:// or https:// URL, got {o.url!r}")
        for key in ("reconnect_initial_s", "reconnect_max_s", "connect_timeout_s"):
            if getattr(o, key) <= 0:
                raise ConfigError(f"{path}.{key}", "must be > 0")

    def __init__(self, options: dict[str, Any], source_id: str):
        super().__init__(options, source_id)
        self.o = SseOptions(**options)
        self.counters = {"connects": 0, "reconnects": 0, "events": 0, "rejected": 0}
        self._sock: socket.socket | None = None
        self._backoff = Backoff(self.o.reconnect_initial_s, self.o.reconnect_max_s)
        self._last_id: str | None = None
        self._reset_stream()

    def _reset_stream(self) -> None:
        self._raw = bytearray()  # bytes from the socket not yet parsed
        self._body = bytearray()  # de-chunked body not yet split into lines
        self._headers_done = False
        self._chunked = False
        self._chunk_left = 0  # bytes left in the current HTTP chunk (chunked mode)
        self._ended = False
        self._data: list[str] = []
        self._etype = ""

    # ------------------------------------------------------------------ connection
    def _connect(self) -> bool:
        u = urlsplit(self.o.url)
        port = u.port or (443 if u.scheme == "https" else 80)
        try:
            s = socket.create_connection((u.hostname, port), timeout=self.o.connect_timeout_s)
            if u.scheme == "https":
                s = ssl.create_default_context().wrap_socket(s, server_hostname=u.hostname)
            path = (u.path or "/") + (f"?{u.query}" if u.query else "")
            hdrs = {"Host": u.netloc, "Accept": "text/event-stream", "Cache-Control": "no-cache",
                    "Connection": "keep-alive", **self.o.headers}
            if self._last_id:
                hdrs["Last-Event-ID"] = self._last_id
            req = f"GET {path} HTTP/1.1\r\n" + "".join(f"{k}: {v}\r\n" for k, v in hdrs.items()) + "\r\n"
            s.sendall(req.encode("latin-1"))
            s.settimeout(5.0)
        except OSError as exc:
            if self.counters["connects"] == 0 and self._backoff.delay == self._backoff.initial:
                log.warning("%s: cannot connect to %s (%s); retrying with backoff", self.source_id, self.o.url, exc)
            self._backoff.failed()
            return False
        self._sock = s
        self._reset_stream()
        return True

    def _drop(self, why: str) -> None:
        log.warning("%s: stream %s ended (%s); reconnecting", self.source_id, self.o.url, why)
        if self._sock is not None:
            try:
                self._sock.close()
            except OSError:
                pass
        self._sock = None
        self._backoff.failed()

    # ------------------------------------------------------------------ parsing
    def _parse_headers(self) -> bool:
        end = self._raw.find(b"\r\n\r\n")
        if end < 0:
            if len(self._raw) > 65536:
                raise _HttpError("response headers too large")
            return False
        head = bytes(self._raw[:end]).decode("latin-1").split("\r\n")
        del self._raw[:end + 4]
        parts = head[0].split(" ", 2)
        if len(parts) < 2 or not parts[0].startswith("HTTP/"):
            raise _HttpError(f"not an HTTP response: {head[0][:80]!r}")
        if parts[1] != "200":
            raise _HttpError(f"HTTP status {head[0][9:80]}")
        hdrs = {k.strip().lower(): v.strip() for k, _, v in (h.partition(":") for h in head[1:])}
        self._chunked = "chunked" in hdrs.get("transfer-encoding", "").lower()
        self._headers_done = True
        if self.counters["connects"]:
            self.counters["reconnects"] += 1
            log.info("%s: reconnected to %s", self.source_id, self.o.url)
        self.counters["connects"] += 1
        self._backoff.ok()
        return True

    def _dechunk(self) -> None:
        raw = self._raw
        if not self._chunked:
            self._body += raw
            raw.clear()
            return
        while raw:
            if self._chunk_left > 0:
                take = min(self._chunk_left, len(raw))
                self._body += raw[:take]
                del raw[:take]
                self._chunk_left -= take
                if self._chunk_left == 0:
                    self._chunk_left = -2  # expect CRLF
                continue
            if self._chunk_left == -2:
                if len(raw) < 2:
                    return
                del raw[:2]
                self._chunk_left = 0
                continue
            eol = raw.find(b"\r\n")
            if eol < 0:
                return
            size_s = bytes(raw[:eol]).split(b";")[0].strip()
            try:
                size = int(size_s, 16)
            except ValueError:
                raise _HttpError(f"bad chunk size {size_s[:20]!r}") from None
            del raw[:eol + 2]
            if size == 0:
                self._ended = True  # parse what came before the last chunk first
                raw.clear()
                return
            self._chunk_left = size

    def _events(self) -> Iterator[str]:
        """Complete events' data from the body buffer (SSE line rules)."""
        body = self._body
        while True:
            # a line ends at \n, \r\n or \r
            cands = [j for j in (body.find(b"\n"), body.find(b"\r")) if j >= 0]
            if not cands:
                if len(body) > MAX_EVENT_BYTES:
                    raise _HttpError("event larger than the limit")
                return
            i = min(cands)
            if body[i:i + 1] == b"\r" and i + 1 >= len(body):
                return  # a lone \r at the end may be half of \r\n
            line = bytes(body[:i]).decode("utf-8", "replace")
            del body[:i + (2 if body[i:i + 2] == b"\r\n" else 1)]
            if not line:
                if self._data:
                    etype = self._etype or "message"
                    data = "\n".join(self._data)
                    self._data, self._etype = [], ""
                    if self.o.event is None or etype == self.o.event:
                        yield data
                self._etype = ""
                continue
            if line.startswith(":"):
                continue
            field, _, value = line.partition(":")
            if value.startswith(" "):
                value = value[1:]
            if field == "data":
                self._data.append(value)
            elif field == "event":
                self._etype = value
            elif field == "id":
                self._last_id = value
            elif field == "retry" and value.isdigit():
                self._backoff.initial = max(0.01, int(value) / 1000.0)

    # ------------------------------------------------------------------ Transport API
    def chunks(self) -> Iterator[Optional[PointChunk]]:
        while True:
            if self._sock is None:
                if not self._backoff.ready() or not self._connect():
                    time.sleep(0.02)
                    yield None
                    continue
            try:
                r, _, _ = select.select([self._sock], [], [], 0.05)
                if not r:
                    yield None
                    continue
                data = self._sock.recv(1 << 20)
                if not data:
                    raise _HttpError("connection closed by the server")
                self._raw += data
                if not self._headers_done and not self._parse_headers():
                    continue
                self._dechunk()
                events = list(self._events())
            except (OSError, _HttpError) as exc:
                self._drop(str(exc))
                yield None
                continue
            if self._ended:
                self._drop("server ended the stream")
            for ev in events:
                self.counters["events"] += 1
                chunk = self.accept(self._parse, ev)
                if chunk is None:
                    continue
                yield chunk
                if self.quota_reached():
                    return

    def _parse(self, event: str) -> PointChunk:
        return parse_json_chunk(event, self.o.max_points, self.source_id)

    def close(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            except OSError:
                pass
            self._sock = None
