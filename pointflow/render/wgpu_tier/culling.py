"""Batch culling in the wgpu tier (:mod:`pointflow.render.batches`).

The CPU keeps per batch of ring slots the bounds of the positions the tier uploads (from the
frames' dirty ranges) and tests the boxes against the float32 frustum planes the shaders get,
with a margin far above float32 rounding (:data:`CULL_REL`); the passes over points then walk
only the runs of the ring between culled whole batches (:func:`.chunks.runs`: each run its
own ``Params`` record and dispatch), so their work scales with the surviving points. The
culled points are added to the counters on the CPU (``removed_nonfinite``: the batches'
non-finite count, ``occupied``); a frame whose ring is larger than the tier's is not culled
(slots beyond are skipped, not counted). Same image on and off: tested.

The automatic colour range's share of the culled batches: with ``color_range: auto`` the shaders reduce the colour value over every occupied point with
a finite position (``ord_f`` words, atomic min/max); a batch culled whole is never read by
them, so the tier seeds that reduction with the culled batches' range, kept here per batch
from the frames' dirty ranges (the staleness :class:`~pointflow.render.batches.BatchBounds`
notes), in the shaders' own terms: the float32 value the tier uploads, its ``ord_f`` word,
min and max of the words (so even -0.0 and +0.0 order as on the GPU).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from ...arrays import finite_rows
from .. import batches
from ..base import FrameInput
from ..batches import BatchBounds
from . import chunks
from .layout import ColourMode, Flag

__all__ = ["BatchColourRange", "CPU_COUNTED", "CULL_REL", "Culling", "ord_f"]

#: the plane margin relative to the sum's magnitude: far above the rounding of the shaders'
#: float32 plane test (a few units of 2^-24), so no point they keep is culled
CULL_REL = 1e-5

_EMPTY = (0xFFFFFFFF, 0)

#: the footprint LOD mask word's flag (batches.LOD_CPU_COUNTED): this batch's non-finite count
#: and colour range are the CPU's (:meth:`Culling.lod_counted`), so the shaders never read its
#: dropped slots
CPU_COUNTED = batches.LOD_CPU_COUNTED


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
            ok = finite_rows(frame.positions[a:b]) & np.isfinite(v)
            if ok.any():
                w = ord_f(v[ok])
                self.lo[k], self.hi[k] = w.min(), w.max()
            else:
                self.lo[k], self.hi[k] = _EMPTY
            self.stale[k] = False
        if not ks.size:
            return _EMPTY
        return int(self.lo[ks].min()), int(self.hi[ks].max())


class Culling:
    """One renderer's batch culling: the bounds and the colour range's share, per batch."""

    def __init__(self, cmode: int, chan: Optional[str], bounds: Optional[BatchBounds] = None):
        self.bounds = bounds if bounds is not None else BatchBounds(batches.BATCH_SLOTS)
        self.crange = BatchColourRange(cmode, chan)
        self.culled = np.zeros(0, np.int64)  # the last :meth:`cut`'s culled batches

    def note(self, frame: FrameInput, everything: bool = False) -> None:
        """Mark the batches this frame's dirty ranges touch (all with ``everything``: the tier
        uploads the whole ring); once per frame, before anything reduces the bounds (the
        compact positions' upload may, before :meth:`cut`)."""
        self.bounds.note(frame, everything)
        self.crange.note(self.bounds)

    def cut(self, frame: FrameInput, P: np.ndarray, segs: list[chunks.Segment], chunk_table: list,
            nseg: int, render_capacity: int) -> tuple[list[chunks.Segment], int, int, Optional[tuple[int, int]]]:
        """(Call :meth:`note` first.) (the runs the point passes walk, empty when nothing is culled; the culled points'
        non-finite count; the culled points; the culled batches' automatic colour range as
        ``ord_f`` words, or None)."""
        none: tuple[list[chunks.Segment], int, int, Optional[tuple[int, int]]] = ([], 0, 0, None)
        self.culled = np.zeros(0, np.int64)
        bb = self.bounds
        cap = int(frame.capacity)
        auto = bool(int(P["flags"]) & Flag.RANGE_AUTO)
        if int(frame.size) == 0 or cap > render_capacity:
            return none
        # the planes exactly as the shaders get them (float32), tested in float64 with a margin
        ks, la = bb.culled(frame, np.asarray(P["planes"], np.float64).reshape(6, 4), rel=CULL_REL)
        if not ks.size:
            return none
        B = bb.batch
        n = np.minimum((ks + 1) * B, cap) - ks * B
        room = [c + chunks.OUT_ALIGN for _, c in chunk_table]
        runs = chunks.runs(segs, la.tolist(), n.tolist(), len(segs), room)
        if runs is None or len(segs) + len(runs) > nseg:
            return none
        zr = None
        if auto:
            w = self.crange.words(frame, ks, B)
            zr = w if w[0] <= w[1] else None
        self.culled = ks
        return runs, int(bb.bad[ks].sum()), int(n.sum()), zr

    def lod_counted(self, frame: FrameInput, masks: np.ndarray, auto: bool,
                    render_capacity: int) -> tuple[np.ndarray, int, int, tuple[int, int]]:
        """(Call after :meth:`cut`.) The footprint LOD's mask words for the shaders, with
        :data:`CPU_COUNTED` on every thinned batch whose slots are all occupied and drawn by
        the tier and that was not culled; those batches' non-finite count and automatic colour
        range (``ord_f`` words; ``(0xFFFFFFFF, 0)`` for none) are then the CPU's (from the
        bounds, as for culled batches), and so is the occupancy of their dropped slots: the
        passes never read a dropped slot (the compute method gives it no thread). Returns
        (words, non-finite count, dropped slots, colour range words)."""
        words = np.asarray(masks, np.uint32).copy()
        bb, cap = self.bounds, int(frame.capacity)
        if bb.batch != 1 << batches.BATCH_SHIFT or cap > render_capacity:
            return words, 0, 0, _EMPTY
        B = bb.batch
        k = np.arange(words.size, dtype=np.int64)
        n = np.minimum((k + 1) * B, cap) - k * B
        flag = batches.lod_countable(words, int(frame.head), int(frame.size), cap, B)
        flag[self.culled[self.culled < words.size]] = False
        ks = np.flatnonzero(flag)
        if not ks.size:
            return words, 0, 0, _EMPTY
        bb.refresh(frame.positions, ks)
        stride = words[ks].astype(np.int64) + 1  # a batch starts at a multiple of its stride
        dropped = int((n[ks] - -(-n[ks] // stride)).sum())
        words[ks] |= np.uint32(CPU_COUNTED)
        return words, int(bb.bad[ks].sum()), dropped, self.crange.words(frame, ks, B) if auto else _EMPTY
