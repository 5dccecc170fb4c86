"""The point loops of the frames step: one rigid transform, or a pose per point, in float64.

Why this shape (measured with bench/bench_frames.py on the shared 2-core VM):

* numpy's ``(N, 3) @ (3, 3)`` goes to OpenBLAS, whose threads cost far more than they save on
  such thin products on a busy machine; products of at most :data:`BLOCK` rows stay on one
  thread, so large clouds go block by block (also keeps each block in cache).
* Broadcasting a (3,) translation over (N, 3) runs numpy's slow 3-wide inner loop; adding a
  flat, tiled copy of it is one fast pass.
* Large fresh arrays cost page faults on every call (several ms per 3 MB on the shared VM);
  intermediates live in :class:`Scratch` buffers that are kept between clouds, so a cloud
  allocates only its result.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

#: Rows per BLAS call (OpenBLAS keeps products this small on one thread).
BLOCK = 16_384


class Scratch:
    """Reusable intermediate arrays, grown on demand (one per Framer: the ingest stage is one
    thread; nothing here outlives a call)."""

    def __init__(self) -> None:
        self._bufs: dict[str, np.ndarray] = {}
        self._tile_key: Optional[bytes] = None
        self._tile: Optional[np.ndarray] = None

    def get(self, name: str, shape: tuple[int, ...], dtype=np.float64) -> np.ndarray:
        """An uninitialised array of ``shape`` (a view on a kept buffer)."""
        size = int(np.prod(shape))
        b = self._bufs.get(name)
        if b is None or b.size < size or b.dtype != dtype:
            b = self._bufs[name] = np.empty(max(size, 1024), dtype)
        return b[:size].reshape(shape)

    def tile(self, t: np.ndarray, rows: int) -> np.ndarray:
        """``t`` (3,) repeated ``rows`` times, flat (cached while ``t`` stays the same)."""
        key = t.tobytes()
        if self._tile is None or self._tile_key != key or self._tile.shape[0] < 3 * rows:
            self._tile = np.tile(np.asarray(t, np.float64), max(rows, 1024))
            self._tile_key = key
        return self._tile[:3 * rows]


def rigid(pos: np.ndarray, R: np.ndarray, t: np.ndarray, scratch: Optional[Scratch] = None,
          out: Optional[np.ndarray] = None) -> np.ndarray:
    """``pos @ R.T + t`` in float64 (pos float32 or float64, (N, 3)); ``out`` may be float32
    (the float64 result rounded once)."""
    n = pos.shape[0]
    if out is None:
        out = np.empty((n, 3), np.float64)
    if n == 0:
        return out
    s = scratch if scratch is not None else Scratch()
    RT = np.ascontiguousarray(R.T, dtype=np.float64)
    m = min(n, BLOCK)
    tile = s.tile(t, m)
    direct = out.dtype == np.float64
    conv = s.get("rigid_in", (m, 3)) if pos.dtype != np.float64 or not pos.flags.c_contiguous else None
    tmp = None if direct else s.get("rigid_out", (m, 3))
    for a in range(0, n, BLOCK):
        b = min(n, a + BLOCK)
        k = b - a
        src = pos[a:b]
        if conv is not None:
            np.copyto(conv[:k], src)
            src = conv[:k]
        dst = out[a:b] if direct else tmp[:k]
        np.matmul(src, RT, out=dst)
        if direct:
            flat = dst.reshape(-1)
            flat += tile[:3 * k]
        else:
            np.add(dst.reshape(-1), tile[:3 * k], out=out[a:b].reshape(-1), casting="unsafe")
    return out
