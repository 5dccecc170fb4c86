"""Span emission: stages record (trace id, event, start, end) and send them in batches.

Wire format on the trace endpoint (PUSH → the supervisor's collector, PULL): one
single-frame message per batch, JSON ``{"stage": name, "pid": pid, "spans": [[trace_id,
event, t0_ns, t1_ns, n_points], ...]}``. Times are ``time.monotonic_ns()``.
"""
from __future__ import annotations

import json
import os
import time

import zmq

#: The events a chunk passes through, in order.
EVENTS = (
    "transport_receive",  # source: chunk produced by the transport
    "ingest_packed",      # ingest: validated and packed into SoA
    "ring_committed",     # ingest: written into the ring
    "cadence_snapshot",   # cadence: first snapshot that contains it
    "render_upload",      # render: uploaded / handed to the tier
    "frame_done",         # render: frame containing it finished (GPU work complete)
)


class SpanEmitter:
    def __init__(self, zctx: zmq.Context | None, endpoint: str | None, stage: str,
                 batch: int = 256, flush_ms: float = 100.0, enabled: bool = True):
        self.stage = stage
        self.enabled = enabled and endpoint is not None and zctx is not None
        self.batch = batch
        self.flush_ns = int(flush_ms * 1e6)
        self._buf: list[list] = []
        self._last = time.monotonic_ns()
        self.sent = 0
        self._sock = None
        if self.enabled:
            self._sock = zctx.socket(zmq.PUSH)
            self._sock.setsockopt(zmq.SNDHWM, 64)
            self._sock.setsockopt(zmq.LINGER, 200)
            self._sock.connect(endpoint)

    def record(self, trace_id: int, event: str, t0_ns: int, t1_ns: int, n: int = 0) -> None:
        if not self.enabled or not trace_id:
            return
        self._buf.append([int(trace_id), event, int(t0_ns), int(t1_ns), int(n)])
        if len(self._buf) >= self.batch:
            self.flush()

    def maybe_flush(self) -> None:
        if self._buf and time.monotonic_ns() - self._last >= self.flush_ns:
            self.flush()

    def flush(self) -> None:
        self._last = time.monotonic_ns()
        if not self._buf or self._sock is None:
            return
        msg = json.dumps({"stage": self.stage, "pid": os.getpid(), "spans": self._buf}, separators=(",", ":"))
        try:
            self._sock.send_string(msg, zmq.NOBLOCK)
            self.sent += len(self._buf)
        except zmq.Again:
            pass  # collector is behind: tracing must never stall the data path
        self._buf = []

    def close(self) -> None:
        self.flush()
        if self._sock is not None:
            self._sock.close()
            self._sock = None
