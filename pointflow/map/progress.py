"""The index build's progress line: percent, points/s, ETA."""
from __future__ import annotations

import sys
import time


class ProgressLine:
    """``map: indexing NAME: 45% (12.3 M of 27.4 M points, 2.1 M points/s, ETA 7 s)`` on stderr,
    redrawn in place on a terminal (see pointflow.stage.console), one line per 10% elsewhere."""

    def __init__(self, name: str, stream=None, min_interval_s: float = 0.5):
        from pointflow.stage.console import is_terminal

        self.name, self.stream = name, stream if stream is not None else sys.stderr
        self.tty = is_terminal(self.stream)
        self.t0 = time.monotonic()
        self.last_t, self.last_decile = 0.0, -1
        self.min_interval_s = min_interval_s

    def __call__(self, done: int, total: int) -> None:
        now = time.monotonic()
        final = done >= total
        frac = done / total if total else 1.0
        decile = int(frac * 10)
        if not final and (now - self.last_t < self.min_interval_s or (not self.tty and decile == self.last_decile)):
            return
        self.last_t, self.last_decile = now, decile
        rate = done / max(now - self.t0, 1e-9)
        eta = (total - done) / rate if rate > 0 else float("inf")
        line = (f"map: indexing {self.name}: {frac:4.0%} ({done / 1e6:.1f} M of {total / 1e6:.1f} M points, "
                f"{rate / 1e6:.2f} M points/s, " + (f"ETA {eta:.0f} s)" if not final else f"{now - self.t0:.1f} s)"))
        if self.tty:
            from pointflow.stage.console import CLEAR_LINE

            self.stream.write(CLEAR_LINE + line + ("\n" if final else ""))
        else:
            self.stream.write(line + "\n")
        self.stream.flush()
