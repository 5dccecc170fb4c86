"""The wgpu tier's incremental upload: only the slot ranges a handoff changed go to the GPU,
chunk by chunk, into the point buffers (``renderer.DATA_SETS`` sets, one today: a frame in
flight keeps reading its own points, since queue writes land after earlier submissions; with
more, each set catches up on the ranges it missed).

A part of :class:`~pointflow.render.wgpu_tier.renderer.WgpuRenderer`, which holds the state
used here: ``queue``, ``_sets`` (per set, per chunk, the named buffers), ``_chunk_table``,
``_pending`` (per set, the ranges not yet written), ``_origin``, ``_last``,
``render_capacity``, ``_compact`` (the compact positions, :mod:`.compact`, or None) and the colour and time settings (``_cmode``, ``_cchan``, ``_need_t``,
``_need_imp``).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..base import FrameInput, merge_ranges
from .layout import ColourMode

__all__ = ["IncrementalUpload"]


class IncrementalUpload:
    """Dirty ranges to the GPU point buffers (mixed into the wgpu renderer)."""

    queue: Any
    render_capacity: int
    _compact: Any

    def _upload(self, frame: FrameInput, s: int) -> int:
        """Write the ranges set ``s`` has missed; returns bytes uploaded."""
        cap = min(self.render_capacity, frame.capacity)
        ranges = merge_ranges(self._pending[s], cap)
        self._pending[s] = []
        total = 0
        if self._compact is not None:
            total += self._compact.upload(frame, s, ranges)
        for a, b in ranges:
            for c, (c0, n) in enumerate(self._chunk_table):
                lo, hi = max(a, c0), min(b, c0 + n)
                if lo < hi:
                    total += self._write(frame, self._sets[s][c], lo, hi, lo - c0)
        return total

    def _write(self, frame: FrameInput, S: dict[str, Any], a: int, b: int, at: int) -> int:
        """Write slots [a, b) into the chunk buffers ``S`` from their slot ``at``; bytes written."""
        q, total = self.queue, 0
        pos = np.ascontiguousarray(frame.positions[a:b], dtype=np.float32)
        q.write_buffer(S["pos"], at * 12, pos)
        total += pos.nbytes
        if self._need_t:
            t64 = np.asarray(frame.t_ingest_ms[a:b], dtype=np.float64)
            tt = np.empty((b - a, 2), np.float32)
            tt[:, 0] = t64
            tt[:, 1] = t64 - tt[:, 0]
            q.write_buffer(S["tms"], at * 8, tt)
            total += tt.nbytes
        if self._need_imp:
            imp = np.ascontiguousarray(frame.importance[a:b], dtype=np.float32)
            q.write_buffer(S["imp"], at * 4, imp)
            total += imp.nbytes
        if self._cmode == ColourMode.RGB:
            rgb = np.asarray(frame.channels["rgb"][a:b], dtype=np.uint32)
            packed = rgb[:, 0] | (rgb[:, 1] << 8) | (rgb[:, 2] << 16) | np.uint32(0xFF000000)
            q.write_buffer(S["col"], at * 4, packed)
            total += packed.nbytes
        elif self._cmode == ColourMode.SCALAR:
            v = np.ascontiguousarray(frame.channels[self._cchan][a:b], dtype=np.float32)
            q.write_buffer(S["col"], at * 4, v)
            total += v.nbytes
        return total

    def _mark_dirty(self, frame: FrameInput) -> bool:
        """Queue the frame's dirty ranges for every data set; True when that is the whole ring (no
        ranges, a new origin or capacity: every position may have changed)."""
        cap = min(self.render_capacity, frame.capacity)
        origin = np.asarray(frame.origin, np.float64)
        full = frame.dirty is None or self._origin is None or not np.array_equal(origin, self._origin) \
            or self._last is None or self._last.capacity != frame.capacity
        d = [(0, cap)] if full else list(frame.dirty or [])
        for s in range(len(self._pending)):
            self._pending[s].extend(d)
            if len(self._pending[s]) > 64:  # keep the list short
                self._pending[s] = merge_ranges(self._pending[s], cap)
        self._origin = origin.copy()
        return bool(full)
