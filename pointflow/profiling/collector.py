"""The supervisor's span collector: a bound PULL draining the stages' span batches.

Spans are kept in preallocated numpy columns (about 40 bytes a span) as a ring of the newest
``max_spans``; older ones are overwritten and counted in ``dropped``, so memory stays bounded
on long runs. Malformed batches are counted (``bad_batches``) and logged, never raised.
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from typing import Optional

import numpy as np
import zmq

from .spans import EVENTS, SPAN_FIELDS

log = logging.getLogger("pointflow.profiling")


@dataclass
class SpanTable:
    """Columns of the kept spans, oldest first. ``event``/``stage`` index the name lists."""

    trace_id: np.ndarray  # uint64
    event: np.ndarray     # int16 -> event_names
    stage: np.ndarray     # int16 -> stage_names
    pid: np.ndarray       # int32
    t0_ns: np.ndarray     # int64, time.monotonic_ns()
    t1_ns: np.ndarray     # int64
    n: np.ndarray         # int64 points
    event_names: list[str]
    stage_names: list[str]

    def __len__(self) -> int:
        return int(self.trace_id.size)


class SpanCollector:
    def __init__(self, zctx: zmq.Context, endpoint: Optional[str], *, max_spans: int = 1_000_000, bind: bool = True):
        if max_spans < 1:
            raise ValueError(f"SpanCollector max_spans must be >= 1, got {max_spans}")
        self.endpoint = endpoint
        self.max_spans = int(max_spans)
        self._sock = None
        if endpoint is not None:
            self._sock = zctx.socket(zmq.PULL)
            self._sock.setsockopt(zmq.LINGER, 0)
            self._sock.setsockopt(zmq.RCVHWM, 10_000)
            (self._sock.bind if bind else self._sock.connect)(endpoint)
        cap = 1024
        self._cols = self._alloc(cap)
        self._cap = cap
        self._count = 0          # spans written in total (kept = min(count, max_spans))
        self.event_names: list[str] = list(EVENTS)
        self._event_idx = {e: i for i, e in enumerate(self.event_names)}
        self.stage_names: list[str] = []
        self._stage_idx: dict[str, int] = {}
        #: pid -> stage name (a restarted stage shows up under a new pid).
        self.processes: dict[int, str] = {}
        self.received = 0
        self.batches = 0
        self.bad_batches = 0
        self.bad_spans = 0

    @staticmethod
    def _alloc(cap: int) -> dict[str, np.ndarray]:
        return {"trace_id": np.zeros(cap, np.uint64), "event": np.zeros(cap, np.int16),
                "stage": np.zeros(cap, np.int16), "pid": np.zeros(cap, np.int32),
                "t0_ns": np.zeros(cap, np.int64), "t1_ns": np.zeros(cap, np.int64), "n": np.zeros(cap, np.int64)}

    @property
    def dropped(self) -> int:
        """Spans overwritten because more than ``max_spans`` arrived."""
        return max(0, self._count - self.max_spans)

    def __len__(self) -> int:
        return min(self._count, self.max_spans)

    # ------------------------------------------------------------------ receive
    def poll(self, timeout_ms: int = 0) -> int:
        """Drain every pending batch (waiting up to ``timeout_ms`` for the first); returns spans added."""
        if self._sock is None:
            return 0
        added = 0
        if timeout_ms and not self._sock.poll(timeout_ms, zmq.POLLIN):
            return 0
        while True:
            try:
                frames = self._sock.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return added
            added += self.add_batch(*frames)

    def add_batch(self, msg: bytes, body: Optional[bytes] = None, *extra: bytes) -> int:
        """Parse one batch (see :mod:`pointflow.profiling.spans`: v2 = JSON header + raw
        uint64 body, v1 = one JSON frame) and store it; returns the spans added."""
        if body is not None or extra:
            return self._add_binary(msg, body, extra)
        self.batches += 1
        try:
            d = json.loads(msg)
            stage, pid, spans = str(d["stage"]), int(d["pid"]), d["spans"]
            if not isinstance(spans, list):
                raise TypeError("'spans' is not a list")
        except (ValueError, KeyError, TypeError, UnicodeDecodeError) as exc:
            self.bad_batches += 1
            if self.bad_batches <= 10:
                log.warning("span collector: bad batch on %s dropped: %s", self.endpoint, exc)
            return 0
        ok = [s for s in spans if isinstance(s, list) and len(s) == 5 and isinstance(s[1], str)]
        self.bad_spans += len(spans) - len(ok)
        if not ok:
            return 0
        try:
            tid = np.array([s[0] for s in ok], dtype=np.uint64)
            t0 = np.array([s[2] for s in ok], dtype=np.int64)
            t1 = np.array([s[3] for s in ok], dtype=np.int64)
            n = np.array([s[4] for s in ok], dtype=np.int64)
        except (ValueError, TypeError, OverflowError) as exc:
            self.bad_batches += 1
            if self.bad_batches <= 10:
                log.warning("span collector: batch from %s[%d] has non-integer fields: %s", stage, pid, exc)
            return 0
        ev = np.array([self._event(s[1]) for s in ok], dtype=np.int16)
        self.processes[pid] = stage
        st = self._stage(stage)
        self._append(tid, ev, st, pid, t0, t1, n)
        self.received += len(ok)
        return len(ok)

    def _bad(self, what: str) -> int:
        self.bad_batches += 1
        if self.bad_batches <= 10:
            log.warning("span collector: bad batch on %s dropped: %s", self.endpoint, what)
        return 0

    def _add_binary(self, head: bytes, body: Optional[bytes], extra) -> int:
        self.batches += 1
        if extra or body is None:
            return self._bad(f"expected 2 frames, got {2 + len(extra) if body is not None else 1}")
        try:
            d = json.loads(head)
            stage, pid, events = str(d["stage"]), int(d["pid"]), d["events"]
            if not isinstance(events, list) or not all(isinstance(e, str) for e in events):
                raise TypeError("'events' is not a list of names")
        except (ValueError, KeyError, TypeError, UnicodeDecodeError) as exc:
            return self._bad(f"header: {exc}")
        body = bytes(body)
        if len(body) % (8 * SPAN_FIELDS):
            return self._bad(f"body of {len(body)} bytes is not a whole number of {8 * SPAN_FIELDS}-byte spans")
        a = np.frombuffer(body, dtype="<u8").reshape(-1, SPAN_FIELDS)
        if a.size == 0:
            return 0
        ev_idx = a[:, 1]
        ok = ev_idx < len(events)
        self.bad_spans += int((~ok).sum())
        a = a[ok]
        if a.size == 0:
            return 0
        remap = np.array([self._event(e) for e in events], dtype=np.int16)
        self.processes[pid] = stage
        self._append(a[:, 0].copy(), remap[a[:, 1].astype(np.intp)], self._stage(stage), pid,
                     a[:, 2].astype(np.int64), a[:, 3].astype(np.int64), a[:, 4].astype(np.int64))
        self.received += int(a.shape[0])
        return int(a.shape[0])

    def _event(self, name: str) -> int:
        i = self._event_idx.get(name)
        if i is None:
            i = self._event_idx[name] = len(self.event_names)
            self.event_names.append(name)
        return i

    def _stage(self, name: str) -> int:
        i = self._stage_idx.get(name)
        if i is None:
            i = self._stage_idx[name] = len(self.stage_names)
            self.stage_names.append(name)
        return i

    def _append(self, tid, ev, st, pid, t0, t1, n) -> None:
        k = tid.size
        if k > self.max_spans:  # only the newest fit
            tid, ev, t0, t1, n = tid[-self.max_spans:], ev[-self.max_spans:], t0[-self.max_spans:], t1[-self.max_spans:], n[-self.max_spans:]
            self._count += k - self.max_spans
            k = self.max_spans
        need = min(self._count + k, self.max_spans)
        if need > self._cap:  # grow (amortised doubling) until max_spans
            cap = min(self.max_spans, max(need, self._cap * 2))
            new = self._alloc(cap)
            for key, arr in self._cols.items():
                new[key][:self._cap] = arr
            self._cols, self._cap = new, cap
        idx = (self._count + np.arange(k)) % self.max_spans
        c = self._cols
        c["trace_id"][idx] = tid
        c["event"][idx] = ev
        c["stage"][idx] = st
        c["pid"][idx] = pid
        c["t0_ns"][idx] = t0
        c["t1_ns"][idx] = t1
        c["n"][idx] = n
        self._count += k

    # ------------------------------------------------------------------ read
    def table(self) -> SpanTable:
        """A copy of the kept spans in arrival order (oldest first)."""
        kept = len(self)
        if self._count <= self.max_spans:
            order = np.arange(kept)
        else:
            start = self._count % self.max_spans
            order = (start + np.arange(kept)) % self.max_spans
        c = self._cols
        return SpanTable(trace_id=c["trace_id"][order], event=c["event"][order], stage=c["stage"][order],
                         pid=c["pid"][order], t0_ns=c["t0_ns"][order], t1_ns=c["t1_ns"][order], n=c["n"][order],
                         event_names=list(self.event_names), stage_names=list(self.stage_names))

    def counters(self) -> dict[str, int]:
        return {"received": self.received, "kept": len(self), "dropped": self.dropped, "batches": self.batches,
                "bad_batches": self.bad_batches, "bad_spans": self.bad_spans}

    def clear(self) -> None:
        self._count = 0

    def close(self) -> None:
        if self._sock is not None:
            self.poll(0)
            self._sock.close(0)
            self._sock = None
