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

from typing import NamedTuple, Optional

import numpy as np

from . import compiled

#: Rows per BLAS call (OpenBLAS keeps products this small on one thread).
BLOCK = 16_384
#: Scratch arrays above this many elements are not kept (a rare huge cloud must not leave
#: hundreds of MB behind); 2**20 covers a 262,144-point sweep's per-point index arrays.
KEEP_MAX = 1 << 20


class Scratch:
    """Reusable intermediate arrays, grown on demand (one per Framer: the ingest stage is one
    thread; nothing here outlives a call)."""

    def __init__(self) -> None:
        self._bufs: dict[str, np.ndarray] = {}
        self._tile_key: Optional[bytes] = None
        self._tile: Optional[np.ndarray] = None

    def get(self, name: str, shape: tuple[int, ...], dtype=np.float64) -> np.ndarray:
        """An uninitialised array of ``shape`` (a view on a kept buffer)."""
        size = 1
        for d in shape:  # not np.prod: ~3 us a call, more than a 1,000-point transform's matmul
            size *= d
        if size > KEEP_MAX:
            return np.empty(shape, dtype)
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
    ks = compiled.load()
    if (ks is not None and out.dtype == np.float64 and out.flags.c_contiguous and pos.flags.c_contiguous
            and pos.dtype.isnative and pos.dtype.char in "fd"):
        # one compiled pass (compiled.py): ~1.9 ns per point against ~7.6, and no per-call
        # numpy overhead (a 1,000-point cloud: ~3 us against ~16)
        ks.rigid64(pos.reshape(-1), np.ascontiguousarray(R, np.float64), np.asarray(t, np.float64).reshape(3),
                   out.reshape(-1))
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
        flat = dst.reshape(-1)
        flat += tile[:3 * k]
        if not direct:  # add in float64, then one rounding copy (faster than a casting add)
            np.copyto(out[a:b].reshape(-1), flat, casting="unsafe")
    return out


class RigidTransform:
    """One rigid transform, applied where the points are written: the ring's push calls
    :meth:`apply` per segment and writes ``R p + (t - origin)`` (float64, rounded once to
    float32) straight into its slots, so a transformed cloud is read once and never stored in
    float64 (``PointRing.push(..., transform=)``)."""

    __slots__ = ("R", "t", "scratch", "_rows", "_kernel", "_v")

    def __init__(self, R: np.ndarray, t: np.ndarray, scratch: Optional[Scratch] = None):
        self.R = np.ascontiguousarray(R, np.float64)
        self.t = np.asarray(t, np.float64)
        self.scratch = scratch if scratch is not None else Scratch()
        #: per output axis (t_r, sum_j R_rj, sum_j |R_rj|) as floats, made by the first bounds()
        self._rows: Optional[tuple] = None
        #: the compiled loop (compiled.py) or None: numpy
        ks = compiled.load()
        self._kernel = ks.rigid if ks is not None else None
        #: (origin bytes, t - origin) of the last apply (a ring's origin rarely changes)
        self._v: Optional[tuple] = None

    def world(self, pos: np.ndarray) -> np.ndarray:
        """The transformed positions, float64 (N, 3)."""
        return rigid(pos, self.R, self.t, self.scratch)

    def apply(self, pos: np.ndarray, origin: np.ndarray, out: np.ndarray) -> None:
        """Write the offsets of the transformed ``pos`` from ``origin`` into ``out`` (flat, any
        float dtype, 3 * N values)."""
        k = self._kernel
        if k is not None and out.dtype == np.float32 and out.flags.c_contiguous and pos.flags.c_contiguous:
            key = origin.tobytes()
            if self._v is None or self._v[0] != key:
                self._v = (key, self.t - origin)
            k(pos.reshape(-1), self.R, self._v[1], out.reshape(-1))
            return
        rigid(pos, self.R, self.t - origin, self.scratch, out=out.reshape(-1, 3))

    def bounds(self, lo: float, hi: float) -> tuple[float, float]:
        """(min, max) over every coordinate of the transformed points, given that every
        coordinate of the points lies in [lo, hi] (interval arithmetic; conservative, widened
        by a relative 1e-9 for the rounding of the product)."""
        if self._rows is None:
            self._rows = tuple(v for r in range(3) for v in (float(self.t[r]), float(self.R[r].sum()),
                                                             float(np.abs(self.R[r]).sum())))
        t0, s0, a0, t1, s1, a1, t2, s2, a2 = self._rows
        c, h = (lo + hi) * 0.5, (hi - lo) * 0.5
        # plain floats, one min and one max (this runs once per chunk: numpy calls would cost
        # ~20 us, a loop with a min/max per axis ~1.8 us)
        m0, m1, m2, r0, r1, r2 = t0 + s0 * c, t1 + s1 * c, t2 + s2 * c, a0 * h, a1 * h, a2 * h
        wlo, whi = min(m0 - r0, m1 - r1, m2 - r2), max(m0 + r0, m1 + r1, m2 + r2)
        return wlo - 1e-9 * (1.0 + abs(wlo)), whi + 1e-9 * (1.0 + abs(whi))


class Placed(NamedTuple):
    """A cloud placed lazily: its positions as sent and the transform the ring applies.
    ``shared``: the same transform object comes with the next clouds too (a static chain),
    so small clouds may still be pushed together."""

    src: np.ndarray
    xf: RigidTransform
    shared: bool
