"""Batches of ring slots with bounds, so a tier culls whole batches before touching points.

The ring's slots are cut into batches of :data:`BATCH_SLOTS`; per batch the bounds of its
finite positions and its non-finite count are kept as the ring is written (only batches a
frame's dirty ranges touch are reduced again, and only when a frame needs them). A batch
whose every slot is occupied, that the ring's head does not cut, and whose box lies wholly
outside one frustum plane (or that holds no finite point) can be skipped whole: none of its
points would survive the frustum test. Every tier uses this one idea: the compiled cpu
raster (``cpu_compute``: its own copy and compiled reductions, the same batches and the same
plane test, :func:`boxes_outside`), the numpy reference and the gl tier through
:class:`BatchBounds` and :func:`pointflow.render.rules.select_points`, and the wgpu tier
through :class:`BatchBounds` (its passes then walk only the surviving runs of the ring:
``wgpu_tier/chunks.py``, :func:`~pointflow.render.wgpu_tier.chunks.runs`).

``POINTFLOW_CPU_RASTER_CULL=0`` (:data:`ENV_CULL`) turns culling off in every tier (same
image: tested).

The same bounds give the footprint LOD (``render.lod_fill``, off by default): a batch whose
box covers few pixels for its points keeps only the slots ``slot % s == 0``, s a power of two
per batch (:func:`lod_masks`), as the map layer picks coarser nodes for far tiles. One
function decides the strides from the bounds, and every tier applies them with the same
per-point test, so the tiers still draw the same points.
"""
from __future__ import annotations

import os
from typing import Optional

import numpy as np

from ..arrays import column_max, column_min, finite_rows
from .base import merge_ranges

__all__ = ["BATCH_SLOTS", "BATCH_SHIFT", "ENV_CULL", "LOD_MAX_STRIDE", "BatchBounds", "box_corners", "boxes_outside",
           "culling_enabled", "lod_masks", "frame_lod_masks", "occupied_per_batch"]

#: Slots per batch: small enough that a view of a tenth of a ring skips most of it, large
#: enough that the per-batch work (bounds, the plane test, one run per batch) stays small.
BATCH_SLOTS = 16384
#: ``slot >> BATCH_SHIFT`` is the slot's batch (the compiled and GPU tests shift, not divide).
BATCH_SHIFT = 14
assert BATCH_SLOTS == 1 << BATCH_SHIFT
#: batches reduced together by :meth:`BatchBounds.refresh` (a scratch copy of 64 x 16384 points)
RUN_BATCHES = 64
#: Footprint LOD: the most a batch is thinned (a power of two, so a stride divides a batch).
LOD_MAX_STRIDE = 64
#: A mask word's flag (bit 31, above every slot index a tier takes, so ``slot & mask`` is
#: unchanged by it): the batch's dropped slots are counted by the tier from the batch's
#: bounds (its non-finite count and colour range), so its loops never read them.
LOD_CPU_COUNTED = 0x80000000
#: Set to 0 to draw without batch culling (the images are the same).
ENV_CULL = "POINTFLOW_CPU_RASTER_CULL"


def culling_enabled() -> bool:
    return os.environ.get(ENV_CULL, "1") not in ("0", "false", "no")


def boxes_outside(lo: np.ndarray, hi: np.ndarray, planes: np.ndarray, rel: float = 1e-9) -> np.ndarray:
    """Per box (rows of ``lo``/``hi``, float64) whether it lies wholly outside one of the
    frustum ``planes`` (n, 4; inside is ``>= 0``). The largest value of each plane over the
    box is at a corner; the box counts as outside only when that is below ``-rel`` (default
    1e-9) relative to the sum's magnitude, far above the rounding of either the per-point or
    the per-box sum, so no point a per-point test would keep is ever culled (a tier that tests
    points in float32, the wgpu tier, passes a larger ``rel``). A box with no finite point
    (infinite bounds) is not outside here (callers cull it by its non-finite count)."""
    nrm, d = planes[:, :3], planes[:, 3]
    with np.errstate(invalid="ignore", over="ignore"):
        # the corner farthest inside each plane: hi where the normal is positive, else lo
        # (as products of (m, 3) by (3, 6): a few numpy calls however many boxes)
        most = d + hi @ np.maximum(nrm, 0.0).T + lo @ np.minimum(nrm, 0.0).T
        scale = np.abs(d) + np.maximum(np.abs(lo), np.abs(hi)) @ np.abs(nrm).T
        return (most < -rel * (scale + 1.0)).any(axis=1)


def occupied_per_batch(head: int, size: int, cap: int, batch: int = BATCH_SLOTS) -> np.ndarray:
    """Occupied slots per batch of a ring (``size`` slots from ``head``, wrapping at ``cap``)."""
    nb = -(-cap // batch) if cap > 0 else 0
    first = np.arange(nb, dtype=np.int64) * batch
    end = np.minimum(first + batch, cap)
    occ = np.zeros(nb, np.int64)
    a = head % cap if cap > 0 else 0
    for s0, s1 in ((a, min(a + size, cap)), (0, max(a + size - cap, 0))):
        occ += np.clip(np.minimum(end, s1) - np.maximum(first, s0), 0, None)
    return occ


def lod_countable(masks: np.ndarray, head: int, size: int, cap: int, batch: int = BATCH_SLOTS) -> np.ndarray:
    """Per batch whether a tier may flag it :data:`LOD_CPU_COUNTED`: thinned (mask above 0)
    and every slot occupied, so its bounds' counts are those of occupied slots; none when a
    slot index could reach the flag's bit. (Culled batches the caller leaves out itself.)"""
    masks = np.asarray(masks)
    if cap > LOD_CPU_COUNTED or not masks.size:
        return np.zeros(masks.size, bool)
    k = np.arange(masks.size, dtype=np.int64)
    whole = occupied_per_batch(head, size, cap, batch)[:masks.size] == np.minimum((k + 1) * batch, cap) - k * batch
    return (masks != 0) & whole


#: which of a box's 8 corners take the high bound, per axis
_CORNERS = np.array([[(c >> i) & 1 for i in range(3)] for c in range(8)], bool)[None]


def box_corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(m, 8, 3) corners of the boxes with rows ``lo``/``hi`` (the footprint LOD's and the
    wgpu tier's compact levels' projections)."""
    return np.where(_CORNERS, hi[:, None, :], lo[:, None, :])


def lod_masks(lo: np.ndarray, hi: np.ndarray, occupied: np.ndarray, vp: np.ndarray, width: int, height: int,
              point_px: float, size_scale: float, fill: float) -> np.ndarray:
    """Footprint LOD: per batch the mask ``s - 1`` (uint32) of its stride s, a power of two
    in 1..:data:`LOD_MAX_STRIDE`: a slot is drawn iff ``slot & mask == 0``. s is the largest
    power of two with ``occupied / s >= fill * area / point_px**2``, ``area`` the pixels of
    the box's projected corners' bounding rectangle (not clipped to the screen: the points'
    density over the box), so about ``fill`` points stay per point-sized cell. A box that
    reaches behind the eye, or has no finite point, keeps every slot. ``size_scale > 0``:
    world-size points, their size in pixels at the box's farthest corner (the smallest, so
    the most points kept), clamped to [1, 4096] as the tiers draw them."""
    nb = lo.shape[0]
    out = np.zeros(nb, np.uint32)
    ok = np.isfinite(lo).all(axis=1) & np.isfinite(hi).all(axis=1) & (occupied > 1)
    if not ok.any() or not fill > 0:
        return out
    everything = ok.all()
    bl, bh, occ = (lo, hi, occupied) if everything else (lo[ok], hi[ok], occupied[ok])
    corners = box_corners(bl, bh)
    vp = np.asarray(vp, np.float64)
    c = corners @ vp[(0, 1, 3), :3].T + vp[(0, 1, 3), 3]  # clip x, y, w of every corner
    w = c[..., 2]
    front = (w > 1e-9).all(axis=1)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # (inf strides: handled below)
        ndc = c[..., :2] / w[..., None]
        ext = ndc.max(axis=1) - ndc.min(axis=1)  # (m, 2): the rectangle in NDC
        area = ext[:, 0] * ext[:, 1] * (0.25 * width * height)
        if size_scale > 0:
            size = np.clip(size_scale / w.max(axis=1), 1.0, 4096.0)
        else:
            size = float(point_px)
        cells = np.maximum(area / (size * size), 1.0)
        stride = occ / (float(fill) * cells)
    # a subnormal fill overflows to +inf: the most thinning, as a tiny fill asks
    stride = np.where(front, np.nan_to_num(stride, nan=1.0, posinf=LOD_MAX_STRIDE), 1.0)
    s = np.exp2(np.floor(np.log2(np.clip(stride, 1.0, LOD_MAX_STRIDE)))).astype(np.uint32) - np.uint32(1)
    if everything:
        return s
    out[ok] = s
    return out


def frame_lod_masks(lo: np.ndarray, hi: np.ndarray, frame, camera, cfg, width: int, height: int,
                    batch: int = BATCH_SLOTS) -> Optional[np.ndarray]:
    """:func:`lod_masks` for a frame drawn with ``cfg`` (None when ``cfg.lod_fill`` is off),
    from the bounds of every batch of the ring (float64 rows, :class:`BatchBounds` or the
    compiled tier's own)."""
    fill = float(cfg.lod_fill)
    if not fill > 0:
        return None
    cap = int(frame.capacity)
    vp = camera.view_proj(width, height, frame.origin)
    world = cfg.point_size_space == "world"
    scale = float(cfg.point_size) * float(camera.proj(width, height)[1, 1]) * height * 0.5 if world else 0.0
    occ = occupied_per_batch(int(frame.head), int(frame.size), cap, batch)
    return lod_masks(lo, hi, occ, vp, width, height, float(cfg.point_size), scale, fill)


class BatchBounds:
    """Bounds per batch of a ring read in place (the numpy and gl tiers read the slab), kept
    from the frames' dirty ranges."""

    def __init__(self, batch: Optional[int] = None):
        self.batch = int(batch or BATCH_SLOTS)
        self.cap = -1
        self.lo = self.hi = np.zeros((0, 3))
        self.bad = np.zeros(0, np.int64)
        self.stale = np.zeros(0, bool)
        # the last plane test per batch, kept while the planes and the batch's bounds stay
        # (a still camera over a live ring tests only the batches rewritten since)
        self._out = np.zeros(0, bool)
        self._out_ok = np.zeros(0, bool)
        self._out_key: Optional[tuple] = None

    def note(self, frame, everything: bool = False) -> None:
        """Mark the batches this frame's dirty ranges touch (all of them for ``None``, a new
        capacity or ``everything``: e.g. a new origin moved every position). Call once per
        frame handed to the tier, before :meth:`culled`."""
        cap = int(frame.capacity)
        if cap != self.cap:
            nb = -(-cap // self.batch)
            self.cap = cap
            self.lo, self.hi = np.full((nb, 3), np.inf), np.full((nb, 3), -np.inf)
            self.bad = np.zeros(nb, np.int64)
            self.stale = np.ones(nb, bool)
            self._out, self._out_ok = np.zeros(nb, bool), np.zeros(nb, bool)
            return
        if frame.dirty is None or everything:
            self.stale[:] = True
            return
        B = self.batch
        for a, b in merge_ranges(frame.dirty, cap):  # a wrapping range (b < a) is split
            self.stale[a // B:(b - 1) // B + 1] = True

    def refresh(self, positions: np.ndarray, ks: np.ndarray) -> None:
        """Reduce the stale batches among ``ks`` (float64 bounds of the finite positions;
        also what the wgpu tier's compact positions are encoded against)."""
        ks = ks[self.stale[ks]]
        if not ks.size:
            return
        B = self.batch
        rest = ks
        if positions.ndim == 2 and positions.shape[1] == 3:
            rest = self._refresh_runs(positions, ks)
        for k in rest:
            p = positions[k * B:min((k + 1) * B, self.cap)]
            n = p.shape[0]
            fin = finite_rows(p)
            self.bad[k] = int(n - np.count_nonzero(fin))
            if self.bad[k] == n:
                self.lo[k], self.hi[k] = np.inf, -np.inf
            else:  # column by column (pointflow.arrays): this runs every frame
                p = p[fin]
                self.lo[k], self.hi[k] = column_min(p), column_max(p)
        self.stale[ks] = False
        if self._out_ok.shape == self.stale.shape:
            self._out_ok[ks] = False  # new bounds: the plane test again

    def _refresh_runs(self, positions: np.ndarray, ks: np.ndarray) -> np.ndarray:
        """The whole batches among ``ks`` whose points are all finite, a run of consecutive
        batches at a time: one copy of the run with the axes as rows, then min and max per
        batch along them (numpy reduces an (n, 3) array's columns 2-3x slower, and a call per
        batch cost more than the reduction). NaN and +-inf reach the extremes, so finite
        extremes mean every position is finite. Returns the batches left to reduce one by one
        (the last, partial batch; those with a non-finite position)."""
        B = self.batch
        whole = ks[(ks + 1) * B <= min(self.cap, positions.shape[0])]
        if not whole.size:
            return ks
        left = [ks[(ks + 1) * B > min(self.cap, positions.shape[0])]]
        cuts = np.flatnonzero(np.diff(whole) != 1) + 1
        for run in np.split(whole, cuts):
            for i in range(0, run.size, RUN_BATCHES):  # bounded scratch (RUN_BATCHES * B points)
                r = run[i:i + RUN_BATCHES]
                k0, m = int(r[0]), int(r.size)
                q = np.ascontiguousarray(positions[k0 * B:(k0 + m) * B].T).reshape(3, m, B)
                lo, hi = q.min(axis=2).T, q.max(axis=2).T
                ok = np.isfinite(lo).all(axis=1) & np.isfinite(hi).all(axis=1)
                self.lo[r[ok]], self.hi[r[ok]] = lo[ok], hi[ok]
                self.bad[r[ok]] = 0
                left.append(r[~ok])
        return np.concatenate(left)

    def lod_masks(self, frame, camera, cfg, width: int, height: int) -> Optional[np.ndarray]:
        """:func:`frame_lod_masks` from these bounds, every batch reduced (None when off)."""
        if not cfg.lod_fill > 0 or int(frame.capacity) <= 0:
            return None
        self.refresh(frame.positions, np.arange(self.lo.shape[0], dtype=np.int64))
        return frame_lod_masks(self.lo, self.hi, frame, camera, cfg, width, height, self.batch)

    def culled(self, frame, planes: np.ndarray, rel: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
        """(batch indices culled whole, their first logical indices), ascending by logical
        index: whole batches (every slot occupied, not cut by the ring's head) outside the
        frustum (:func:`boxes_outside` with ``rel``) or without a finite point."""
        cap, size, head = self.cap, int(frame.size), int(frame.head)
        B = self.batch
        if size <= 0 or cap <= 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        k = np.arange(self.lo.shape[0], dtype=np.int64)
        first = k * B
        n = np.minimum(first + B, cap) - first
        la = (first - head) % cap  # logical index of the batch's first slot
        # whole: its slots are logical [la, la + n) within the occupied [0, size), no wrap
        whole = (la + n <= size) & ~((head > first) & (head < first + n))
        ks = k[whole]
        if not ks.size:
            return ks, ks
        self.refresh(frame.positions, ks)
        out = self._outside(ks, planes, rel) | (self.bad[ks] == n[ks])
        ks = ks[out]
        order = np.argsort(la[ks], kind="stable")
        return ks[order], la[ks][order]

    def _outside(self, ks: np.ndarray, planes: np.ndarray, rel: float) -> np.ndarray:
        """:func:`boxes_outside` of the batches ``ks`` (reduced), tested again only where the
        planes or a batch's bounds changed since the last call."""
        planes = np.ascontiguousarray(planes, np.float64)
        key = (planes.tobytes(), float(rel))
        if key != self._out_key or self._out_ok.shape != self.stale.shape:
            self._out_key = key
            self._out, self._out_ok = np.zeros(self.stale.shape, bool), np.zeros(self.stale.shape, bool)
        todo = ks[~self._out_ok[ks]]
        if todo.size:
            self._out[todo] = boxes_outside(self.lo[todo], self.hi[todo], planes, rel)
            self._out_ok[todo] = True
        return self._out[ks]

    def survivors(self, frame, planes: np.ndarray) -> Optional[tuple[np.ndarray, int, int]]:
        """The logical indices left after culling whole batches, with the culled points'
        non-finite count and total; None when nothing is culled (the caller takes every
        occupied index)."""
        ks, la = self.culled(frame, planes)
        if not ks.size:
            return None
        B, size, cap = self.batch, int(frame.size), self.cap
        n = np.minimum((ks + 1) * B, cap) - ks * B
        starts = np.concatenate([[0], la + n])
        ends = np.concatenate([la, [size]])
        keep = ends > starts
        runs = [np.arange(a, b, dtype=np.int64) for a, b in zip(starts[keep], ends[keep])]
        logical = np.concatenate(runs) if runs else np.zeros(0, np.int64)
        return logical, int(self.bad[ks].sum()), int(n.sum())
