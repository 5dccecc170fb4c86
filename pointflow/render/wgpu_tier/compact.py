"""Compact positions for the compute raster method (Schütz et al. 2022, precision levels).

Per batch of ring slots (:class:`~pointflow.render.batches.BatchBounds`, the culling's own
bounds) each position is stored relative to its batch's box in 30 bits per axis, split over
three u32 words per point: ``coarse`` (the 10 high bits of x, y, z), ``medium`` (the next
10) and ``fine`` (the low 10); bit 31 of ``coarse`` marks a non-finite position. Per frame
the tier picks per batch how many words the raster pass reads, from the box's projected size
in pixels: the fewest whose quantisation moves no point by more than :data:`TOL_PX` pixels
(first-order bound over the box), or the float32 positions (level 0) where even 30 bits do
not reach it or the box reaches behind the camera. A far batch then costs 4 bytes per point,
a near one 8 or 12, instead of 12 for three floats. The float32 positions stay uploaded
(resolve, picking, colour by z and level 0 read them), so memory grows by 12 B per slot.

Decoding (raster.wgsl ``load_pos``): ``lo + (c + 0.5) * ext / 2^10`` for coarse only,
``lo + c * ext / 2^10 + (m + 0.5) * ext / 2^20`` with medium, and so on; each term is exact
in float32, so level 3 is as precise as the float32 positions.

Only *settled* batches are encoded: a batch whose slots no frame has written for
:data:`SETTLE_FRAMES` frames (``POINTFLOW_WGPU_COMPACT_SETTLE``), whole, at most
:data:`ENCODE_POINTS_PER_FRAME` points per frame; until then, and from the frame a slot of
it is written again, it is read at level 0 (its float32 positions, uploaded every frame in
any case). Why: encoding costs the CPU some 13 ns a point in numpy, while the bytes it saves
can save at most the raster pass's time, which an H100 spent at 0.04 ns a point a frame
(0.69 ms for 16M). A point of a live ring rewritten 1% per frame is drawn some 100 frames:
at most 3-4 ns saved for 13 spent, and the CPU side is most of a frame on a GPU. Points that
stay (a replayed survey, a map) are encoded once and read in 4-8 bytes for as long as they
stay. ``SETTLE=0`` encodes every written batch at once, and then only the written ranges
while its box holds (the first version's policy; the benchmark of the raster pass uses it).

A batch is encoded with the bounds its buffer set holds (one set: ``renderer.DATA_SETS``).
Each set keeps its own bounds and table (lo, level; step). The levels and the table are
worked out again only for boxes that changed, or for all of them when the view changed: a
still camera over a live ring chooses levels for the rewritten batches alone.

``POINTFLOW_WGPU_COMPACT`` (:data:`ENV_COMPACT`): ``0`` draws from the float32 positions
only, ``1`` compact; unset, compact except on a CPU adapter (:func:`compact_choice`).
"""
from __future__ import annotations

import os
from typing import Any, Optional

import numpy as np

from ..base import FrameInput, merge_ranges
from ..batches import BatchBounds, box_corners

__all__ = ["BITS", "ENCODE_POINTS_PER_FRAME", "ENV_COMPACT", "ENV_SETTLE", "LEVEL_NAMES", "SETTLE_FRAMES",
           "TOL_PX", "CompactPositions", "compact_choice", "encode", "choose_levels", "settle_frames"]

#: 0: the float32 positions only (the full-precision path); 1: compact; unset: auto
ENV_COMPACT = "POINTFLOW_WGPU_COMPACT"
#: frames a batch's slots stay unwritten before the batch is encoded (0: at once, always)
SETTLE_FRAMES = 120
ENV_SETTLE = "POINTFLOW_WGPU_COMPACT_SETTLE"
#: the most points encoded per frame (whole batches, at least one; not with SETTLE 0): a ring
#: that settles at once (a file loaded whole) is encoded over several frames, not in one
ENCODE_POINTS_PER_FRAME = 65_536
#: bits per axis read at level 1, 2, 3
BITS = (10, 20, 30)
#: the largest move of a point (pixels, first-order bound over the batch's box) a level may
#: cause. Measured (bench_wgpu_compact.py scene, 4M points, whole ring in view at 1280x720):
#: 1/16 px let 85% of the batches read coarse words and changed 1.7% of the pixels (dense
#: points: footprint edges and near-equal depths), over the agreement tests' 1%; 1/64 px
#: changed 0.005%
TOL_PX = 1.0 / 64.0
#: level -> name, bytes of position read per point in the raster pass
LEVEL_NAMES = {0: "float32", 1: "coarse", 2: "medium", 3: "fine"}
LEVEL_BYTES = {0: 12, 1: 4, 2: 8, 3: 12}
_LEVEL_BYTES = np.array([LEVEL_BYTES[v] for v in range(4)], np.int64)
_Q = float(1 << 30)


def compact_choice(adapter_type: str, raster: str = "compute", naive_float32: bool = False) -> tuple[bool, str]:
    """(compact on, why): only the compute method (quads: float32 positions), never with the
    tests' naive float32 transform; ``POINTFLOW_WGPU_COMPACT=1`` on, ``0`` off; unset
    (``auto``): on unless the adapter is a CPU (lavapipe), where the decode's arithmetic costs
    more than the bytes it saves (measured: bench/bench_wgpu_compact.py, docs/render-tiers.md)."""
    if raster != "compute" or naive_float32:
        return False, "naive_float32 (tests)" if naive_float32 else f"not with the {raster} method"
    v = os.environ.get(ENV_COMPACT, "auto").strip().lower()
    if v in ("0", "false", "no", "off"):
        return False, f"{ENV_COMPACT}={v}"
    if v in ("1", "true", "yes", "on"):
        return True, f"{ENV_COMPACT}={v}"
    if adapter_type == "CPU":
        return False, "auto: off on a CPU adapter (slower there; POINTFLOW_WGPU_COMPACT=1 forces it)"
    return True, f"auto: on ({adapter_type or 'unknown'} adapter)"


def settle_frames() -> int:
    """:data:`SETTLE_FRAMES`, or ``POINTFLOW_WGPU_COMPACT_SETTLE`` (a whole number >= 0)."""
    v = os.environ.get(ENV_SETTLE, "").strip()
    if not v:
        return SETTLE_FRAMES
    try:
        n = int(v)
    except ValueError:
        n = -1
    if n < 0:
        raise ValueError(f"{ENV_SETTLE} must be a whole number of frames >= 0, got {v!r}")
    return n


def encode(p: np.ndarray, lo: np.ndarray, ext: np.ndarray) -> np.ndarray:
    """(3, n) uint32 words (coarse, medium, fine) of float positions ``p`` (n, 3) relative to
    the box ``lo``/``ext`` (float64, (3,) or per point (n, 3)); non-finite rows get bit 31 of
    coarse. Axis by axis on contiguous columns (1.8x faster than on (n, 3) rows: this runs on
    every frame's rewritten slots)."""
    lo, ext = np.asarray(lo, np.float64), np.asarray(ext, np.float64)
    per = lo.ndim == 2
    n = p.shape[0]
    bad = np.zeros(n, bool)
    us = []
    with np.errstate(invalid="ignore"):  # (non-finite rows: zeroed next)
        for a in range(3):
            la, ea = (lo[:, a], ext[:, a]) if per else (lo[a], ext[a])
            u = np.asarray(p[:, a], np.float64) - la
            bad |= ~np.isfinite(u)
            u *= np.where(ea > 0, _Q / np.where(ea > 0, ea, 1.0), 0.0)
            us.append(u)
    any_bad = bool(bad.any())
    out = np.zeros((3, n), np.uint32)
    m = np.uint32(0x3FF)
    for a, u in enumerate(us):
        if any_bad:
            u[bad] = 0.0
        np.clip(u, 0.0, _Q - 1.0, out=u)
        q = u.astype(np.uint32)  # floor: u >= 0; 30 bits per axis
        sh = np.uint32(10 * a)
        out[0] |= (q >> np.uint32(20)) << sh
        out[1] |= ((q >> np.uint32(10)) & m) << sh
        out[2] |= (q & m) << sh
    out[0, bad] |= np.uint32(0x80000000)
    return out


def choose_levels(lo: np.ndarray, hi: np.ndarray, vp: np.ndarray, vw: float, vh: float,
                  planes: Optional[np.ndarray] = None, tol_px: Optional[float] = None) -> np.ndarray:
    """Per box (rows of ``lo``/``hi``; float64) the level the raster pass reads: the fewest
    bits whose quantisation (half a step per axis) moves no point of the box that projects
    near the image (|ndc| <= 2) by more than ``tol_px`` pixels (first order); 0 (float32)
    where 30 bits do not reach it, the box reaches behind the camera, or the near or far
    plane of ``planes`` (the frustum's six, inside >= 0) cuts it (a point exactly on those
    planes is kept as the float32 path keeps it; a decoded point stays inside its box, so
    a box on one side stays there); 1 for a box without a finite point. ``vp``: the
    view-projection (row-major)."""
    tol_px = TOL_PX if tol_px is None else float(tol_px)
    nb = lo.shape[0]
    lev = np.ones(nb, np.int64)
    ok = np.isfinite(lo).all(axis=1) & np.isfinite(hi).all(axis=1)
    if not ok.any():
        return lev
    L, H = lo[ok], hi[ok]
    corners = box_corners(L, H)  # (m, 8, 3)
    clip = corners @ vp[:, :3].T + vp[:, 3]
    w = clip[..., 3]
    wmin = w.min(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        rx = np.minimum(np.abs(clip[..., 0] / w).max(axis=1), 2.0)
        ry = np.minimum(np.abs(clip[..., 1] / w).max(axis=1), 2.0)
    ext = H - L
    front = wmin > 1e-6 * np.maximum(np.abs(w).max(axis=1), 1.0)
    if planes is not None:  # the near and far planes, both at once
        pl = planes[4:6]
        d = corners @ pl[:, :3].T + pl[:, 3]  # (m, 8, 2)
        m = 1e-5 * (np.abs(pl[:, 3]) + np.abs(corners).max(axis=(1, 2))[:, None] * np.abs(pl[:, :3]).sum(axis=1)
                    + 1.0)
        front &= ~((d.min(axis=1) <= m) & (d.max(axis=1) >= -m)).any(axis=1)
    A = np.abs(vp)
    # the largest move per axis at b bits is 0.5 * ext / 2^b: a power of two apart per level,
    # so the pixel moves are those at 0 bits scaled exactly by 2^-b
    e = 0.5 * ext
    wsafe = np.where(front, wmin, 1.0)
    dx = 0.5 * vw / wsafe * (e @ A[0, :3] + rx * (e @ A[3, :3]))
    dy = 0.5 * vh / wsafe * (e @ A[1, :3] + ry * (e @ A[3, :3]))
    most = np.maximum(dx, dy)
    out = np.where(most * 2.0 ** -30 <= tol_px, 3, 0)
    out = np.where(most * 2.0 ** -20 <= tol_px, 2, out)
    out = np.where(most * 2.0 ** -10 <= tol_px, 1, out)
    lev[ok] = np.where(front, out, 0)
    return lev


class CompactPositions:
    """The compact words of one renderer: per buffer set, per chunk a ``qpos`` buffer (coarse,
    medium and fine arrays of the chunk's length, one after the other), per set a table of
    two vec4 per batch (lo.xyz, level; ext / 2^10 .xyz, 0) and the bounds it was encoded with."""

    def __init__(self, device: Any, bounds: BatchBounds, capacity: int, chunk_table: list[tuple[int, int]],
                 sets: int = 1):
        import wgpu
        BU = wgpu.BufferUsage
        self.device, self.queue, self.bounds = device, device.queue, bounds
        self.batch = bounds.batch
        self.capacity = int(capacity)
        self.chunk_table = chunk_table
        self.nb = -(-self.capacity // self.batch)
        sto = BU.STORAGE | BU.COPY_DST
        self.qpos = [[device.create_buffer(size=max(n * 12, 16), usage=sto, label=f"qpos{s}.{c}")
                      for c, (_, n) in enumerate(chunk_table)] for s in range(sets)]
        self.table = [device.create_buffer(size=max(self.nb * 32, 32), usage=sto, label=f"qtab{s}")
                      for s in range(sets)]
        self.lo = [np.full((self.nb, 3), np.nan) for _ in range(sets)]
        self.hi = [np.full((self.nb, 3), np.nan) for _ in range(sets)]
        # per set: the levels and table last written, the view they were chosen for, and the
        # boxes encoded anew since (their levels and table rows are due)
        self._lev = [np.zeros(self.nb, np.int64) for _ in range(sets)]
        self._table = [np.zeros((self.nb, 8), np.float32) for _ in range(sets)]
        self._view: list[Optional[tuple]] = [None] * sets
        self._due = [np.ones(self.nb, bool) for _ in range(sets)]
        self._n = np.minimum((np.arange(self.nb) + 1) * self.batch, self.capacity) - np.arange(self.nb) * self.batch
        self.settle = settle_frames()
        # per set: which batches' words hold their slots (encoded against self.lo/hi[s]); per
        # batch: frames since a frame last wrote one of its slots
        self.encoded = [np.zeros(self.nb, bool) for _ in range(sets)]
        self.age = np.zeros(self.nb, np.int64)
        self.levels = np.zeros(self.nb, np.int64)
        self.stats: dict[str, Any] = {}

    def upload(self, frame: FrameInput, s: int, ranges: list[tuple[int, int]]) -> int:
        """The slots of ``ranges`` (merged, within the tier's slots) were written. Settling
        (``settle`` > 0): their batches are read at level 0 again from this frame and encoded
        once settled (:meth:`frame`); nothing is written here. ``settle`` 0: the slots are
        encoded into set ``s`` now, a batch whose bounds changed since set ``s`` encoded it
        whole. Bytes written."""
        if not ranges:
            return 0
        B, cap = self.batch, min(self.capacity, int(frame.capacity))
        ks = np.unique(np.concatenate([np.arange(a // B, (b - 1) // B + 1) for a, b in ranges]))
        ks = ks[ks < min(self.nb, self.bounds.lo.shape[0])]
        if self.settle > 0:
            self.age[ks] = 0
            enc = self.encoded[s]
            self._due[s][ks[enc[ks]]] = True  # their table rows: level 0 from this frame
            enc[ks] = False
            return 0
        self.encoded[s][ks] = True
        self.bounds.refresh(frame.positions, ks)
        lo, hi = self.bounds.lo[ks], self.bounds.hi[ks]
        same = ((lo == self.lo[s][ks]) | (np.isinf(lo) & np.isinf(self.lo[s][ks]))).all(axis=1) & \
               ((hi == self.hi[s][ks]) | (np.isinf(hi) & np.isinf(self.hi[s][ks]))).all(axis=1)
        whole = [(int(k) * B, min((int(k) + 1) * B, cap)) for k in ks[~same]]
        self.lo[s][ks], self.hi[s][ks] = lo, hi
        self._due[s][ks[~same]] = True
        writes = merge_ranges(list(ranges) + whole, cap)
        total = 0
        for a, b in writes:
            for c, (c0, n) in enumerate(self.chunk_table):
                x, y = max(a, c0), min(b, c0 + n)
                if x < y:
                    total += self._write(frame, s, c, n, x, y, x - c0)
        return total

    def _write(self, frame: FrameInput, s: int, c: int, n: int, a: int, b: int, at: int) -> int:
        B = self.batch
        words = np.empty((3, b - a), np.uint32)
        for k in range(a // B, (b - 1) // B + 1):  # per batch: its box
            x, y = max(a, k * B), min(b, (k + 1) * B)
            lo, hi = self.lo[s][k], self.hi[s][k]
            fin = bool(np.isfinite(lo).all() and np.isfinite(hi).all())
            words[:, x - a:y - a] = encode(frame.positions[x:y], lo if fin else np.zeros(3),
                                           hi - lo if fin else np.zeros(3))
        for i in range(3):
            self.queue.write_buffer(self.qpos[s][c], (i * n + at) * 4, words[i])
        return words.nbytes

    def settle_step(self, frame: FrameInput, s: int) -> int:
        """One frame of settling: every batch a frame older; the settled batches not yet
        encoded (oldest slots first, at most :data:`ENCODE_POINTS_PER_FRAME` points) encoded
        whole into set ``s`` against their bounds now. Bytes written."""
        if self.settle <= 0:
            return 0
        np.minimum(self.age + 1, 1 << 40, out=self.age)
        cap = min(self.capacity, int(frame.capacity))
        ks = np.flatnonzero(~self.encoded[s] & (self.age > self.settle))  # written ``settle`` frames ago
        ks = ks[ks * self.batch < cap]
        if not ks.size:
            return 0
        ks = ks[:max(1, ENCODE_POINTS_PER_FRAME // self.batch)]
        self.bounds.refresh(frame.positions, ks)
        self.lo[s][ks], self.hi[s][ks] = self.bounds.lo[ks], self.bounds.hi[ks]
        self.encoded[s][ks] = True
        self._due[s][ks] = True
        B, total = self.batch, 0
        for a, b in merge_ranges([(int(k) * B, min((int(k) + 1) * B, cap)) for k in ks], cap):
            for c, (c0, n) in enumerate(self.chunk_table):
                x, y = max(a, c0), min(b, c0 + n)
                if x < y:
                    total += self._write(frame, s, c, n, x, y, x - c0)
        return total

    def frame(self, s: int, P: np.ndarray, forced: int = -1) -> None:
        """Choose the levels for the view of the frame's ``Params`` ``P`` (its float32
        view-projection, viewport and planes, as the shaders get them) from set ``s``'s boxes
        and write its table (``forced`` >= 0: that level for every encoded box, tests); a
        batch not encoded reads level 0."""
        view = (P["vp"].tobytes(), float(P["vw"]), float(P["vh"]), P["planes"].tobytes(), int(forced))
        due = self._due[s]
        if view != self._view[s]:
            due[:] = True
            self._view[s] = view
        ks = np.flatnonzero(due)
        if not ks.size:  # same view, same boxes: the table on the GPU holds these levels
            return
        vp = np.asarray(P["vp"], np.float64).reshape(4, 4).T  # (stored column-major)
        vw, vh = float(P["vw"]), float(P["vh"])
        planes = np.asarray(P["planes"], np.float64).reshape(6, 4)
        lo, hi = self.lo[s][ks], self.hi[s][ks]
        lev = self._lev[s]
        lev[ks] = choose_levels(lo, hi, vp, vw, vh, planes) if forced < 0 else forced
        lev[ks[~self.encoded[s][ks]]] = 0  # (its words do not hold its slots)
        fin = np.isfinite(lo).all(axis=1) & np.isfinite(hi).all(axis=1)
        T = self._table[s]
        T[ks, :3] = np.where(fin[:, None], lo, 0.0)
        T[ks, 3] = lev[ks].astype(np.uint32).view(np.float32)
        T[ks, 4:7] = np.where(fin[:, None], (hi - lo) / 1024.0, 0.0)
        a, b = int(ks[0]), int(ks[-1]) + 1  # one write of the rows between the first and last due
        self.queue.write_buffer(self.table[s], a * 32, T[a:b])
        due[:] = False
        self.levels = lev.copy()
        counts = {LEVEL_NAMES[v]: int(c) for v, c in zip(LEVEL_NAMES, np.bincount(lev, minlength=4))}
        bpp = float((_LEVEL_BYTES[lev] * self._n).sum() / max(int(self._n.sum()), 1))
        self.stats = {"compact_levels": counts, "compact_position_bytes_per_point": bpp,
                      "compact_encoded_batches": int(np.count_nonzero(self.encoded[s]))}

    def close(self) -> None:
        for b in [*self.table, *(x for per in self.qpos for x in per)]:
            try:
                b.destroy()
            except Exception:
                pass

