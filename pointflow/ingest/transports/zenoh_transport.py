"""``zenoh``: receive chunks published by ``pointflow send`` with ``engine: zenoh``.

Subscribes the key expression ``key`` (default ``pointflow/**``): a wildcard picks up
every sensor published under it, each with its own source id (the chunk header's
``source``), as one ``zmq`` source takes several senders. Messages are the single-buffer
framing of :func:`pointflow.wire.to_single` (header in the attachment), decoded by
:mod:`pointflow.wire` (plain, compressed, quantised); ``lost_in_transit`` per source comes
from the ``link`` header (:mod:`pointflow.remote.transit`), exactly as on a ZeroMQ link.

Zenoh delivers samples on its own threads. The callback never blocks and never decodes:
it appends the sample to a bounded queue (``queue_chunks``); when the source loop is
behind, the oldest sample is dropped and its header kept, so its points are counted per
source as ``receive_queue_full`` (``link_sent = link_received + lost_in_transit +
receive_queue_full``). ``backpressure: true`` (lossless replays) makes the callback wait
for room instead.

Dead senders: each sender holds a liveliness token on its source's key. When a token goes
away without the source's final sync (a sender killed, a network gone), the source logs
it and counts ``senders_lost``; ``senders_alive`` is the number of tokens seen now.
"""
from __future__ import annotations

import collections
import dataclasses
import importlib.util
import json
import logging
import threading
import time
from dataclasses import field
from typing import Any, Iterator, Optional

from ... import wire
from ...chunk import ChunkError, PointChunk
from ...remote.options import check_key_expr
from ...remote.transit import TransitLedger
from ...remote.zenoh_options import CONFIRM_PARAMETERS, ZenohOptions, check_zenoh
from ...typed import ConfigError, at_least_one, check, load_dataclass
from ._backoff import NetworkOptions
from .base import Transport

log = logging.getLogger("pointflow.transport.zenoh")

#: Where a receiver connects unless its zenoh block says otherwise: a sender's default listen.
DEFAULT_CONNECT = "tcp/127.0.0.1:7448"
#: A token that disappears is judged this long later: the final sync may still be on its way.
DEATH_GRACE_S = 1.0
#: Headers of dropped samples kept for the accounting; beyond this they count as lost_in_transit.
DROPPED_HEADERS_MAX = 100_000


@dataclasses.dataclass
class ZenohSourceOptions(NetworkOptions):
    #: Key expression to subscribe; ``*`` and ``**`` pick up many senders (each its own source).
    key: str = "pointflow/**"
    #: The session; by default a peer that connects to tcp/127.0.0.1:7448 (a local sender).
    zenoh: ZenohOptions = field(default_factory=ZenohOptions)
    #: Samples held between Zenoh and the source loop; beyond, the oldest is dropped (counted).
    queue_chunks: int = field(default=64, metadata=check(at_least_one))
    #: true: with the queue full, Zenoh's receiving thread waits instead (nothing dropped
    #: here; the network and, with ``send.backpressure``, the sender wait too). For lossless
    #: replays one-to-one: it stalls this whole session, and through a router every viewer.
    backpressure: bool = False


class ZenohTransport(Transport):
    name = "zenoh"
    options_schema = ZenohSourceOptions

    @classmethod
    def check_options(cls, o: ZenohSourceOptions, path: str, base_dir: str) -> None:
        check_key_expr(o.key, f"{path}.key", wildcards=True)
        if o.zenoh.mode == "router":
            raise ConfigError(f"{path}.zenoh.mode", "a receiving source is a peer or a client; run routers with "
                              "`pointflow router`")
        check_zenoh(o.zenoh, f"{path}.zenoh", base_dir, connect_default=(DEFAULT_CONNECT,))
        if importlib.util.find_spec("zenoh") is None:  # every stage loads the config: no engine import here
            raise ConfigError(f"{path}", "the zenoh transport needs eclipse-zenoh: pip install 'pointflow[remote]'")

    def __init__(self, options: dict[str, Any], source_id: str):
        super().__init__(options, source_id)
        self.o: ZenohSourceOptions = load_dataclass(ZenohSourceOptions, options, "options")
        #: with backpressure the source stage also waits for ingest instead of dropping (hwm)
        self.lossless = self.o.backpressure
        self.counters = {"messages": 0, "rejected": 0, "receive_queue_full": 0, "receive_queue_full_chunks": 0,
                         "senders_alive": 0, "senders_lost": 0}
        self.ledger = TransitLedger()
        self._lock = threading.Condition()  # the queues; notified when the source loop took a sample
        self._closing = False
        self._queue: collections.deque = collections.deque()
        #: Headers (bytes) of samples dropped from the queue, oldest first; all older than the queue's.
        self._dropped: collections.deque = collections.deque()
        self._dropped_uncounted = 0
        self._wake = threading.Event()
        self._events: collections.deque = collections.deque()  # (key, alive) of liveliness tokens
        self._alive: set[str] = set()
        self._gone: dict[str, float] = {}  # key -> when its token went away
        self._session = None
        self._subs: list = []

    # ---------------------------------------------------------------- Zenoh threads
    def _on_sample(self, sample) -> None:
        """Zenoh's thread: queue, drop the oldest beyond the bound; nothing else."""
        item = (sample.payload, sample.attachment)
        with self._lock:
            while self.o.backpressure and len(self._queue) >= self.o.queue_chunks and not self._closing:
                self._lock.wait(0.1)
            self._queue.append(item)
            if len(self._queue) > self.o.queue_chunks:
                _, att = self._queue.popleft()
                if len(self._dropped) < DROPPED_HEADERS_MAX:
                    self._dropped.append(att.to_bytes() if att is not None else b"")
                else:
                    self._dropped_uncounted += 1
        self._wake.set()

    def _on_query(self, query) -> None:
        """Zenoh's thread: a closing sender asks whether its final sync has been taken here
        (``remote.zenoh_sender.confirm_delivery``); the payload names its source."""
        if str(query.parameters) != CONFIRM_PARAMETERS:
            return
        src = query.payload.to_bytes().decode("utf-8", "replace") if query.payload is not None else ""
        query.reply(query.key_expr, b"ended" if src in self.ledger.ended else b"pending")

    def _on_token(self, sample) -> None:
        import zenoh

        self._events.append((str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT))
        self._wake.set()

    # ---------------------------------------------------------------- source loop
    def open(self) -> None:
        from ...remote.zenoh_options import open_session

        self._session = open_session(self.o.zenoh)
        try:
            self._subs.append(self._session.declare_subscriber(self.o.key, self._on_sample))
            self._subs.append(self._session.declare_queryable(self.o.key, self._on_query))
            self._subs.append(self._session.liveliness().declare_subscriber(self.o.key, self._on_token, history=True))
        except Exception as exc:  # noqa: BLE001 - a ZError: one line, no traceback
            self.close()
            raise RuntimeError(f"zenoh transport: cannot subscribe {self.o.key!r}: {exc}") from None
        where = ", ".join([f"listen {x}" for x in self.o.zenoh.listen] + [f"connect {x}" for x in self.o.zenoh.connect])
        log.info("%s: subscribed zenoh %s (%s; %s)", self.source_id, self.o.key, self.o.zenoh.mode, where)

    def _liveliness(self) -> None:
        while self._events:
            key, alive = self._events.popleft()
            if alive:
                self._gone.pop(key, None)
                if key not in self._alive:
                    log.info("%s: sender of %s is alive", self.source_id, key)
                self._alive.add(key)
            elif key in self._alive:
                self._alive.discard(key)
                self._gone[key] = time.monotonic()
        now = time.monotonic()
        for key, t in list(self._gone.items()):
            if now - t < DEATH_GRACE_S:
                continue
            del self._gone[key]
            src = key.rsplit("/", 1)[-1]
            if src in self.ledger.ended or any(s in self.ledger.ended for s in self.ledger.streams
                                               if key.endswith("/" + s)):
                continue  # it stopped cleanly: its final sync came
            self.counters["senders_lost"] += 1
            log.warning("%s: the sender of %s is gone (its liveliness token disappeared without a final sync: "
                        "killed, or the network to it is down); what it sent last is counted when it returns",
                        self.source_id, key)
        self.counters["senders_alive"] = len(self._alive)

    def _take(self):
        """The next dropped header (True, bytes) or queued sample (False, item), oldest first."""
        with self._lock:
            if self._dropped:
                return True, self._dropped.popleft()
            if self._queue:
                item = self._queue.popleft()
                self._lock.notify()
                return False, item
            self._wake.clear()
            return None, None

    def _account_dropped(self, header: bytes) -> None:
        try:
            h = json.loads(header)
            link, src, n = h.get("link"), h.get("source") or self.source_id, h.get("n")
            if not isinstance(n, int) or isinstance(n, bool) or n < 0:
                raise ChunkError("bad_count", f"point count must be a non-negative integer, got {n!r}")
            if link is not None:
                if not self.ledger.observe(src, link, n, dropped=True) and isinstance(link, dict) and link.get("sync"):
                    return  # a sync: its totals are taken all the same, no points were lost
        except ChunkError as exc:
            self.reject(exc.reason, f"(a dropped message) {exc}")
            return
        except Exception as exc:  # noqa: BLE001 - not JSON
            self.reject("bad_header", f"(a dropped message) header is not JSON: {exc}")
            return
        self.counters["receive_queue_full_chunks"] += 1

    def parse(self, item) -> Optional[PointChunk]:
        payload, att = item
        if att is None:
            raise ChunkError("bad_frame_count", "a zenoh message without the header attachment (not pointflow's "
                             "single-buffer framing)")
        frames = wire.from_single(att.to_bytes(), payload.to_bytes())
        chunk, header = wire.decode_message(frames, self.o.max_points)
        link = header.get("link")
        if link is not None:
            src = chunk.source_id or self.source_id
            if not self.ledger.observe(src, link, chunk.n):  # a sync: totals only
                if src in self.ledger.ended:
                    t = self.ledger.per_source()[src]
                    log.info("%s: sender of %r stopped: sent %d, received %d, lost in transit %d point(s)%s",
                             self.source_id, src, t["sent"], t["received"], t["lost_points"],
                             f", dropped here (queue full) {t['dropped']}" if t.get("dropped") else "")
                return None
        return chunk

    def chunks(self) -> Iterator[Optional[PointChunk]]:
        while True:
            self._liveliness()
            got = 0
            while got < 64:
                dropped, item = self._take()
                if dropped is None:
                    break
                if dropped:
                    self._account_dropped(item)
                    continue
                got += 1
                self.counters["messages"] += 1
                chunk = self.accept(self.parse, item)
                self.counters.update(self.ledger.counters())
                if chunk is None:  # rejected (counted) or a link sync
                    continue
                yield chunk
                if self.quota_reached():
                    return
            self.counters["receive_queue_full_uncounted"] = self._dropped_uncounted
            if not got:
                self._wake.wait(0.05)
                yield None

    def close(self) -> None:
        with self._lock:
            self._closing = True
            self._lock.notify_all()
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:  # noqa: BLE001 - already gone with the session
                pass
        self._subs.clear()
        if self._session is not None:
            self._session.close()
            self._session = None
        with self._lock:
            self._queue.clear()
