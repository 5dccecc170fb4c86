"""A deterministic clock: ``sleep`` advances time (plus optional oversleep) instead of waiting."""
from __future__ import annotations


class FakeClock:
    def __init__(self, t: float = 100.0, oversleep: float = 0.0):
        self.t = t
        self.oversleep = oversleep
        self.sleeps: list[float] = []

    def __call__(self) -> float:
        return self.t

    def sleep(self, s: float) -> None:
        self.sleeps.append(s)
        self.t += max(s, 0.0) + self.oversleep

    def advance(self, s: float) -> None:
        self.t += s
