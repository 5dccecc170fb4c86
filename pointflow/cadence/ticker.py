"""Absolute-deadline ticker with injectable clock and sleep (testable with a fake clock).

Deadlines are ``anchor + k * interval``: a late tick never pushes the next one back, so the
achieved rate does not drift. When the caller wakes after one or more *further* deadlines
have already passed, those deadlines are skipped and counted (``missed``); only the most
recent passed deadline is served. Nothing is ever queued.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, Optional

Clock = Callable[[], float]
Sleep = Callable[[float], None]


@dataclass(frozen=True)
class Tick:
    """One served tick. ``late_s`` = how long after its deadline it was served."""

    index: int          # deadline number since the anchor (gaps = skipped ticks)
    deadline: float     # seconds on ``clock``
    now: float
    late_s: float
    missed: int         # deadlines skipped just before this one (unservable)


class Ticker:
    """Fires at ``interval_s`` on absolute deadlines.

    ``wait(idle=..., max_wait_s=...)`` spends the time until the next deadline in
    ``idle(timeout_s)`` (e.g. polling a socket; defaults to ``sleep``) and finishes with a
    short precise ``sleep``; it returns ``None`` if ``max_wait_s`` ran out first, so a stage
    loop can heartbeat and check for stop between ticks.
    """

    def __init__(self, interval_s: float, *, clock: Clock = time.monotonic, sleep: Sleep = time.sleep,
                 spin_s: float = 0.002, start: Optional[float] = None):
        if not interval_s > 0:
            raise ValueError(f"Ticker interval must be > 0 s, got {interval_s!r}")
        self.clock = clock
        self.sleep = sleep
        self.spin_s = float(spin_s)
        self._interval = float(interval_s)
        now = clock() if start is None else float(start)
        self._anchor = now          # deadline k is anchor + k * interval
        self._k = 1                 # next deadline index (first tick one interval after start)
        self.ticks = 0
        self.missed = 0

    @property
    def interval_s(self) -> float:
        return self._interval

    @property
    def next_deadline(self) -> float:
        return self._anchor + self._k * self._interval

    def set_interval(self, interval_s: float) -> None:
        """Change the period; the next deadline becomes ``last deadline + interval_s``."""
        if not interval_s > 0:
            raise ValueError(f"Ticker interval must be > 0 s, got {interval_s!r}")
        if abs(interval_s - self._interval) < 1e-12:
            return
        last = self._anchor + (self._k - 1) * self._interval
        self._anchor = last
        self._k = 1
        self._interval = float(interval_s)

    def poll(self) -> Optional[Tick]:
        """Serve the due tick if its deadline has passed (no waiting), else ``None``."""
        now = self.clock()
        deadline = self.next_deadline
        if now < deadline:
            return None
        # Whole further periods that also passed are unservable: skip, count, never queue.
        extra = int(math.floor((now - deadline) / self._interval))
        k = self._k + extra
        served_deadline = self._anchor + k * self._interval
        if served_deadline > now:  # float rounding at an exact boundary
            k -= 1
            extra -= 1
            served_deadline = self._anchor + k * self._interval
        self._k = k + 1
        self.ticks += 1
        self.missed += extra
        return Tick(index=k, deadline=served_deadline, now=now, late_s=now - served_deadline, missed=extra)

    def wait(self, idle: Optional[Callable[[float], None]] = None, max_wait_s: Optional[float] = None) -> Optional[Tick]:
        """Block until the next deadline (or ``max_wait_s``); return the tick or ``None``."""
        start = self.clock()
        limit = None if max_wait_s is None else start + max_wait_s
        while True:
            tick = self.poll()
            if tick is not None:
                return tick
            now = self.clock()
            if limit is not None and now >= limit:
                return None
            target = self.next_deadline if limit is None else min(self.next_deadline, limit)
            left = target - now
            if idle is not None and left > self.spin_s:
                idle(left - self.spin_s)  # coarse part (socket poll has ms granularity)
            else:
                self.sleep(max(left, 0.0))
