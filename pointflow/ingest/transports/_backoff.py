"""Reconnect backoff and the options every network transport shares."""
from __future__ import annotations

import dataclasses
import time


@dataclasses.dataclass
class NetworkOptions:
    """Options of every network transport (subclasses add theirs after these)."""

    #: Chunks larger than this are rejected (``too_large``).
    max_points: int = 5_000_000
    #: Reconnect backoff: first delay, doubling up to the maximum.
    reconnect_initial_s: float = 0.1
    reconnect_max_s: float = 5.0
    #: websocket and sse: TCP connect and handshake timeout (ZeroMQ connects lazily).
    connect_timeout_s: float = 3.0
    #: Stop after this many chunks (0 = never); for tests and captures.
    max_chunks: int = 0


class Backoff:
    """Exponential backoff: ``initial`` doubling up to ``maximum`` seconds; reset on success."""

    def __init__(self, initial: float = 0.1, maximum: float = 5.0):
        self.initial = initial
        self.maximum = maximum
        self.delay = initial
        self.next_try = 0.0

    def failed(self) -> None:
        self.next_try = time.monotonic() + self.delay
        self.delay = min(self.maximum, self.delay * 2)

    def ok(self) -> None:
        self.delay = self.initial
        self.next_try = 0.0

    def ready(self) -> bool:
        return time.monotonic() >= self.next_try
