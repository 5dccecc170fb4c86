"""What this machine gives more threads right now: a compute-bound and a streaming numba
loop, timed in the same rounds as the cpu raster (``bench_cpu_threads.py``), so that the
raster's speed-up is read against the machine's own. On a shared VM the second vCPU's gain
moves between runs (a plain compute loop measured 1.5x in one minute and 2.0x in the next):
a raster ratio alone cannot tell the code's scaling from the host's."""
from __future__ import annotations

import time
from typing import Any

import numpy as np

numba: Any = None
_kernels: Any = None


def _compute_loop(a, out):
    """Independent arithmetic per item: no memory traffic to share."""
    for i in numba.prange(out.size):
        s = 0.0
        x = a[i]
        for j in range(256):
            s += np.sin(x + j)
        out[i] = s


def _stream_loop(a, b):
    """One read and one write per element, far beyond the caches."""
    for i in numba.prange(a.size):
        b[i] = a[i] * 2.0 + 1.0


def _compile() -> Any:
    global numba, _kernels
    if _kernels is None:
        import numba as nb
        numba = nb
        _kernels = (nb.njit(parallel=True, cache=True)(_compute_loop), nb.njit(parallel=True, cache=True)(_stream_loop))
    return _kernels


class Ceiling:
    """Times both loops at the current numba thread count, each sized to about ``ms`` at
    one thread on this machine (a frame's length, so wake-up costs weigh as in a frame)."""

    def __init__(self, ms: float = 8.0) -> None:
        self.compute, self.stream = _compile()
        a = np.random.default_rng(0).random(4096)
        self._a, self._out = a, np.empty_like(a)
        self._x = np.random.default_rng(1).random(1 << 21)
        self._y = np.empty_like(self._x)
        prev = numba.get_num_threads()
        numba.set_num_threads(1)
        try:
            self._time_compute(), self._time_stream()  # compiled (or loaded) and warm
            items = int(np.clip(len(a) * ms / max(self._time_compute(), 1e-3), 256, 1 << 20))
            self._a = np.random.default_rng(0).random(items)
            self._out = np.empty_like(self._a)
            elems = int(np.clip(len(self._x) * ms / max(self._time_stream(), 1e-3), 1 << 16, 1 << 25))
            self._x = np.random.default_rng(1).random(elems)
            self._y = np.empty_like(self._x)
        finally:
            numba.set_num_threads(prev)

    def _time_compute(self) -> float:
        t0 = time.perf_counter()
        self.compute(self._a, self._out)
        return (time.perf_counter() - t0) * 1e3

    def _time_stream(self) -> float:
        t0 = time.perf_counter()
        self.stream(self._x, self._y)
        return (time.perf_counter() - t0) * 1e3

    def time(self, repeat: int = 3) -> dict[str, float]:
        """Median ms of each loop over ``repeat`` calls at the current thread count."""
        c = [self._time_compute() for _ in range(repeat)]
        s = [self._time_stream() for _ in range(repeat)]
        return {"compute": float(np.median(c)), "stream": float(np.median(s))}
