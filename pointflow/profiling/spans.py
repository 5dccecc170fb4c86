"""Span emission: stages record (trace id, event, start, end, points) and send them in batches.

Wire format on the trace endpoint (PUSH → the supervisor's collector, PULL), one two-frame
message per batch:

* frame 0: JSON ``{"v": 2, "stage": name, "pid": pid, "events": [event names]}``;
* frame 1: little-endian uint64 array of shape (k, 5): ``trace_id, event index (into
  "events"), t0_ns, t1_ns, n_points``.

Times are ``time.monotonic_ns()``. Recording a span is an ``array.extend`` (well under a
microsecond); a batch costs one small JSON header and one raw frame, so tracing stays far
below 2 % of the stages' work (``bench/bench_latency.py`` measures it). The collector also
accepts the v1 format: one JSON frame ``{"stage", "pid", "spans": [[tid, event, t0, t1, n], ...]}``.
"""
from __future__ import annotations

import array
import json
import os
import time

import zmq

#: The events a chunk passes through, in order.
EVENTS = (
    "transport_receive",  # source: chunk produced by the transport
    "transform",          # ingest: placed in the fixed frame (docs/frames.md; waiting for transforms included)
    "ingest_packed",      # ingest: validated and packed into SoA
    "ring_committed",     # ingest: written into the ring
    "cadence_snapshot",   # cadence: first snapshot that contains it
    "render_upload",      # render: uploaded / handed to the tier
    "frame_done",         # render: frame containing it finished (GPU work complete)
)
SPAN_FIELDS = 5
_MASK64 = (1 << 64) - 1


class SpanEmitter:
    """Buffers spans and sends them every ``batch`` spans or ``flush_ms`` (non-blocking: when
    the collector is behind a batch is dropped and counted, never stalling the data path)."""

    def __init__(self, zctx: zmq.Context | None, endpoint: str | None, stage: str,
                 batch: int = 256, flush_ms: float = 100.0, enabled: bool = True):
        self.stage = stage
        self.enabled = enabled and endpoint is not None and zctx is not None
        self.batch = max(1, int(batch))
        self.flush_ns = int(flush_ms * 1e6)
        self._events: list[str] = list(EVENTS)
        self._event_idx = {e: i for i, e in enumerate(self._events)}
        self._buf = array.array("Q")
        self._n = 0
        self._last = time.monotonic_ns()
        self.sent = 0
        self.dropped = 0
        self._sock = None
        if self.enabled:
            self._sock = zctx.socket(zmq.PUSH)
            self._sock.setsockopt(zmq.SNDHWM, 64)
            self._sock.setsockopt(zmq.LINGER, 200)
            self._sock.connect(endpoint)

    def record(self, trace_id: int, event: str, t0_ns: int, t1_ns: int, n: int = 0) -> None:
        if not self.enabled or not trace_id:
            return
        i = self._event_idx.get(event)
        if i is None:
            i = self._event_idx[event] = len(self._events)
            self._events.append(event)
        try:
            self._buf.extend((trace_id & _MASK64, i, t0_ns, t1_ns, n))
        except (OverflowError, TypeError):  # negative or non-integer: clamp (drop a partial row first)
            del self._buf[self._n * SPAN_FIELDS:]
            self._buf.extend((int(trace_id) & _MASK64, i, max(0, int(t0_ns)), max(0, int(t1_ns)), max(0, int(n))))
        self._n += 1
        if self._n >= self.batch:
            self.flush()

    def maybe_flush(self) -> None:
        if self._n and time.monotonic_ns() - self._last >= self.flush_ns:
            self.flush()

    def flush(self) -> None:
        self._last = time.monotonic_ns()
        if not self._n or self._sock is None:
            return
        head = json.dumps({"v": 2, "stage": self.stage, "pid": os.getpid(), "events": self._events},
                          separators=(",", ":")).encode()
        body = self._buf.tobytes() if array.array("Q").itemsize == 8 and _little() else _le(self._buf)
        try:
            self._sock.send_multipart([head, body], zmq.NOBLOCK)
            self.sent += self._n
        except zmq.Again:
            self.dropped += self._n  # collector is behind: tracing must never stall the data path
        self._buf = array.array("Q")
        self._n = 0

    def close(self) -> None:
        self.flush()
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def _little() -> bool:
    import sys

    return sys.byteorder == "little"


def _le(buf: array.array) -> bytes:  # pragma: no cover - big-endian hosts
    import numpy as np

    return np.frombuffer(buf.tobytes(), dtype=f"={buf.typecode}").astype("<u8").tobytes()
