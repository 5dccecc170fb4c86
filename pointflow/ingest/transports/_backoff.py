"""Reconnect backoff shared by the network transports."""
from __future__ import annotations

import time


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
