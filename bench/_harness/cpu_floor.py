"""The cpu raster's bare floor for bench/bench_render.py: the same threads, split and
chunks, projection and key write as the render stage's ``raster`` loop
(pointflow/render/cpu_kernels.py), no rules. Benchmark-only, so it lives here and is
compiled here, calling the render stage's own compiled ``_splat``."""
from __future__ import annotations

from typing import Any, Callable

import numpy as np

from pointflow.render import cpu_kernels

numba: Any = None
EMPTY = cpu_kernels.EMPTY
_splat: Any = None
_tile_grid: Any = None
_compiled: Callable[..., None] | None = None


def _floor(keys, T, C, bands, pos, size, head, cap, W, H, vp, half_px):
    """The benchmark's bare floor: the same threads, split and chunks, projection and key
    write as :func:`_raster`, no rules (no tests but w > 0, square footprint, no colour, no
    resolve)."""
    if not bands:
        for r in numba.prange(T * H):
            t = r // H
            y = r - t * H
            for i in range(y * W, (y + 1) * W):
                keys[t, i] = EMPTY
    TW, TH = _tile_grid(W, H)
    for c in numba.prange(C):
        tm = np.zeros(TW * TH, np.uint8)  # the tiles _splat marks (a scratch: cleared whole)
        if bands:
            kb = keys[0]
            ylo = H * c // T
            yhi = H * (c + 1) // T
            for i in range(ylo * W, yhi * W):
                kb[i] = EMPTY
            a = 0
            b = size
        else:
            kb = keys[numba.get_thread_id()]
            ylo = 0
            yhi = H
            a = size * c // C
            b = size * (c + 1) // C
        for logical in range(a, b):
            slot = head + logical
            if slot >= cap:
                slot -= cap
            x = np.float64(pos[slot, 0])
            y = np.float64(pos[slot, 1])
            z = np.float64(pos[slot, 2])
            w = vp[3, 0] * x + vp[3, 1] * y + vp[3, 2] * z + vp[3, 3]
            if not w > 0.0:
                continue
            cx = vp[0, 0] * x + vp[0, 1] * y + vp[0, 2] * z + vp[0, 3]
            cy = vp[1, 0] * x + vp[1, 1] * y + vp[1, 2] * z + vp[1, 3]
            _splat(kb, tm, TW, logical, cx, cy, w, W, H, half_px, False, 0.0, False, ylo, yhi)


def floor_kernel() -> Callable[..., None] | None:
    """The compiled floor (None without numba): ``fn(keys, T, C, bands, pos, size, head,
    cap, W, H, vp, half_px)``."""
    global numba, _splat, _tile_grid, _compiled
    if _compiled is None:
        if cpu_kernels.load() is None:  # compiles the render loops and their inline helpers
            return None
        import numba as nb

        numba, _splat, _tile_grid = nb, cpu_kernels._splat, cpu_kernels._tile_grid
        _compiled = nb.njit(parallel=True, nogil=True, boundscheck=False, error_model="numpy")(_floor)
    return _compiled
