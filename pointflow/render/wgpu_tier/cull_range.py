"""The automatic colour range's share of the batches the wgpu tier culls.

With ``color_range: auto`` the shaders reduce the colour value over every occupied point with
a finite position (``ord_f`` words, atomic min/max); a batch culled whole is never read by
them, so the tier seeds that reduction with the culled batches' range, kept here per batch
from the frames' dirty ranges (the staleness :class:`~pointflow.render.batches.BatchBounds`
notes), in the shaders' own terms: the float32 value the tier uploads, its ``ord_f`` word,
min and max of the words (so even -0.0 and +0.0 order as on the GPU).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from ..base import FrameInput
from ..batches import BatchBounds
from .layout import ColourMode

__all__ = ["BatchColourRange", "ord_f"]

_EMPTY = (0xFFFFFFFF, 0)


def ord_f(v: np.ndarray) -> np.ndarray:
    """float32 -> order-preserving uint32 (``ord_f`` of common.wgsl)."""
    b = np.ascontiguousarray(v, np.float32).view(np.uint32)
    return np.where(b & 0x80000000, ~b, b | 0x80000000).astype(np.uint32)


class BatchColourRange:
    """Per batch: (min, max) ``ord_f`` word of the colour value over its finite points."""

    def __init__(self, cmode: int, chan: Optional[str]):
        self.cmode, self.chan = int(cmode), chan
        self.lo = np.zeros(0, np.uint32)
        self.hi = np.zeros(0, np.uint32)
        self.stale = np.zeros(0, bool)

    def note(self, bb: BatchBounds) -> None:
        """Take the staleness ``bb.note`` just marked (call after it, before ``bb.culled``)."""
        if self.stale.shape != bb.stale.shape:
            self.lo = np.full(bb.stale.shape, _EMPTY[0], np.uint32)
            self.hi = np.full(bb.stale.shape, _EMPTY[1], np.uint32)
            self.stale = np.ones(bb.stale.shape, bool)
        self.stale |= bb.stale

    def values(self, frame: FrameInput, a: int, b: int) -> np.ndarray:
        """The float32 colour values of slots [a, b), as the tier uploads them."""
        if self.cmode == ColourMode.Z:
            return np.asarray(frame.positions[a:b, 2], np.float32)
        if self.cmode == ColourMode.TIME:
            return np.asarray(frame.t_ingest_ms[a:b], np.float64).astype(np.float32)
        return np.asarray(frame.channels[self.chan][a:b], np.float32)

    def words(self, frame: FrameInput, ks: np.ndarray, batch: int) -> tuple[int, int]:
        """(min, max) ``ord_f`` word over the batches ``ks`` (``(0xFFFFFFFF, 0)``: none)."""
        cap = int(frame.capacity)
        for k in ks[self.stale[ks]]:
            a, b = int(k) * batch, min((int(k) + 1) * batch, cap)
            v = self.values(frame, a, b)
            ok = np.isfinite(frame.positions[a:b]).all(axis=1) & np.isfinite(v)
            if ok.any():
                w = ord_f(v[ok])
                self.lo[k], self.hi[k] = w.min(), w.max()
            else:
                self.lo[k], self.hi[k] = _EMPTY
            self.stale[k] = False
        if not ks.size:
            return _EMPTY
        return int(self.lo[ks].min()), int(self.hi[ks].max())
