"""The cpu tier's compiled raster method (``render: {backend: cpu, raster: compute}``).

The wgpu compute method's semantics on the CPU, compiled with numba
(:mod:`.cpu_kernels`), parallel over the cores:

1. **Incremental copy**: the tier keeps its own float32 copy of positions and of what the
   config draws with (importance, ingest times, the colour channel; rgb packed to 32 bits),
   and takes only the handoff's dirty slot ranges (everything after an origin or capacity
   change), as the wgpu tier uploads.
2. **Tests + keys**: every rule of :mod:`.rules` fused with the float64 projection and a
   write of ``bits(float32 w) << 32 | logical`` into each pixel of the footprint, the
   smallest key winning: nearer linear depth, ties to the lower logical index. Split
   ``bins`` (issue 41): per chunk of slots the points' records sorted by screen band, then
   each band keyed in a thread's own in-cache buffer and resolved (no shared writes, nothing
   to merge), whole batches outside the frustum culled from bounds kept as the copy is
   written; split ``points``: one key buffer per thread, merged in the resolve; ``auto``
   times both. With a budget below the survivors, three short passes first (tests,
   thinning, the first b in logical order).
3. **Resolve**: per pixel the smallest key (keys are unique, so the image is the same
   whatever the thread count or split), its colour, and EDL over the winners' log2 depth.
   Picking reads the winners' slots of the last frame.

The float64 numpy tier (:mod:`.cpu`, ``raster: reference``) stays the accuracy reference.
"""
from __future__ import annotations

import os
import time
from typing import Any, Optional

import numpy as np

from .config import RenderConfig
from . import colormap, cpu_kernels
from .base import FrameInput, FrameStats, Renderer, RenderError, merge_ranges
from .batches import (BATCH_SLOTS, LOD_CPU_COUNTED, boxes_outside, culling_enabled, frame_lod_masks,
                      lod_countable)
from .camera import Camera, planes_of
from .rules import (EDL_SCALE, budget_fraction, budget_seed, check_frame, edl_offsets, in_pick_circle, pick_window,
                    resolve_pick, rgba_u8, seed_hash)

__all__ = ["CpuComputeRenderer"]

ENV_SPLIT = "POINTFLOW_CPU_RASTER_SPLIT"
#: how the threads share the work (bench/bench_render.py --cpu-raster measures them)
SPLITS = ("auto", "bins", "points", "bands")
#: auto without measurements: points for a frame drawn with at most POINTS_UP_TO_THREADS
#: threads, else bins (points measured faster here at every size from 10k to 1M points with
#: the ring in view, at 1 and 2 threads, since its key buffers are cleared and resolved by
#: tile: few buffers, no records to sort; bins culls whole batches, so a view of a small
#: part of a big ring favours it: the adaptive choice measures both)
DEFAULT_SPLIT = "auto"
POINTS_UP_TO_THREADS = 2
#: split by bins: logical indices per chunk of the binning pass (its scratch stays in cache)
BIN_CHUNK = BATCH_SLOTS
#: split by bins: rows per screen band, 2^BAND_SHIFT (a thread's band of keys, rows x width x 8
#: bytes, stays in cache)
BAND_SHIFT = 4
#: split by bins: whole batches (render/batches.py, BATCH_SLOTS) whose bounds lie outside the
#: frustum are culled (env POINTFLOW_CPU_RASTER_CULL=0: never)
#: split by bins: first guess of records per point (a box crossing a band edge is in two bands)
RECORDS_PER_POINT = 1.125
#: split by points: chunks of logical indices per thread, taken as threads come free
CHUNKS_PER_THREAD = 8
ENV_ADAPTIVE = "POINTFLOW_CPU_RASTER_ADAPTIVE"
#: frames timed per thread count before choosing; the other count is re-tried every RETRY_EVERY
TUNE_FRAMES = 3
RETRY_EVERY = 30
#: the footprint LOD off: no masks (the kernels' per-batch test is skipped)
_NO_LOD = np.zeros(0, np.uint32)



class _Bins:
    """The binned raster's records of the last frame (one for every target size: they scale
    with the ring; picking reads them)."""

    def __init__(self) -> None:
        self.C = 0          # chunks drawn
        self.RC = 0         # records per chunk region
        self.BS = BAND_SHIFT
        self.BH = 1 << BAND_SHIFT
        self.NB = 0         # bands (bucket NB: boxes over MAX_BANDS_PER_POINT bands)
        self.rkey = np.zeros(1, np.uint64)
        self.rbox = np.zeros(1, np.uint64)
        self.rf = np.zeros((1, 3), np.float64)
        self.off = np.zeros((0, 2), np.int64)

    def ready(self, chunks: int, per_chunk: int, round_: bool, H: int) -> None:
        """Room for ``chunks`` regions of ``per_chunk`` records (grown, never shrunk)."""
        self.NB = -(-H // self.BH)
        n = chunks * per_chunk
        if self.rkey.shape[0] < n or self.RC != per_chunk:
            self.RC = per_chunk
            self.rkey = np.empty(max(n, 1), np.uint64)
            self.rbox = np.empty(max(n, 1), np.uint64)
        if round_ and self.rf.shape[0] < n:
            self.rf = np.empty((max(n, 1), 3), np.float64)
        if self.off.shape != (chunks, self.NB + 2):
            self.off = np.zeros((chunks, self.NB + 2), np.int64)
        self.C = chunks


def use_mask_of(frame: FrameInput, size: int) -> bool:
    """A budget below the occupied count: the budget's passes decide the points first."""
    return frame.budget is not None and size > max(int(frame.budget), 0)


def _pack(c: np.ndarray) -> np.uint32:
    c = np.asarray(c, np.uint32)
    return np.uint32(c[0] | (c[1] << 8) | (c[2] << 16) | (c[3] << 24))


class CpuComputeRenderer(Renderer):
    """Compiled CPU raster with the wgpu compute method's key and rules."""

    tier = "cpu"
    raster = "compute"
    keeps_data = True

    def __init__(self, cfg: RenderConfig, capacity: int, channels: list[str]):
        super().__init__(cfg, capacity, channels)
        k = cpu_kernels.load()
        if k is None:
            raise RenderError(f"cpu compute raster unavailable: {cpu_kernels.why_unavailable()}")
        self._k = k
        self._raster_why = "render.raster=compute"
        W, H = self.width, self.height
        self._bg = _pack(rgba_u8(cfg.background))
        self._single = _pack(rgba_u8(cfg.color))
        self._lut = np.ascontiguousarray(colormap.lut(cfg.colormap)).view(np.uint32).reshape(256)
        self._img = np.empty((H, W), np.uint32)
        self._img[:] = self._bg
        self._shown = self._tiles(W, H)  # tiles of the image that may hold more than background
        self._last_ring = (0, 1)  # head, capacity of the last frame (slots from its keys)
        self._edl = edl_offsets(cfg.edl.radius_px).astype(np.int64) if cfg.edl.enabled else None
        self._logz = np.zeros(H * W if self._edl is not None else 1, np.float64)
        self._keys = np.empty((0, H * W), np.uint64)
        self._marks = np.ones((0, 1), np.uint8)  # per key buffer, the tiles it may hold keys in
        #: how the threads share the work: bins (records sorted by screen band, then each band
        #: keyed and resolved by one thread), points (one key buffer per thread, merged in the
        #: resolve), bands (one key buffer, every thread runs every point and writes its rows),
        #: auto (bins; points for one thread over many points); env POINTFLOW_CPU_RASTER_SPLIT
        split = os.environ.get(ENV_SPLIT, "").strip().lower() or DEFAULT_SPLIT
        if split not in SPLITS:
            raise RenderError(f"${ENV_SPLIT}={split!r}: expected one of {', '.join(SPLITS)}")
        self.split_mode = split
        self.split = "bins" if split == "auto" else split  # the last frame's
        self.bands = split == "bands"
        self._bins = _Bins()
        self._records_per_point = RECORDS_PER_POINT
        self._cull = culling_enabled()
        self.culled_points = 0  # points of the last frame in batches culled whole
        self._bin_scratch: tuple = ()
        self._drew = False
        self.threads = 1
        #: thread count chosen per frame by measurement (env POINTFLOW_CPU_RASTER_ADAPTIVE=0: always all)
        self._adaptive = os.environ.get(ENV_ADAPTIVE, "1") not in ("0", "false", "no")
        self._tune: dict[int, list[float]] = {}
        self._tune_n = 0
        self.frames_at: dict[int, int] = {}  # frames drawn per thread count
        self.frames_by: dict[tuple[str, int], int] = {}  # frames drawn per (split, thread count)
        self._origin: Optional[np.ndarray] = None
        self._cap = -1
        cb = cfg.color_by
        self._need_t = cfg.time_window_ms > 0 or cb == "ingest_time"
        self._need_imp = cfg.importance_sampling or cfg.pick_strategy == "highest_importance"
        self._need_t = self._need_t or cfg.pick_strategy == "recent_first"
        self._alloc(max(int(capacity), 1))
        self.nonfinite_total = 0
        self.frames = 0
        self._warm()

    # ---------------------------------------------------------------- own copy
    def _alloc(self, cap: int) -> None:
        self._cap = cap
        self._pos = np.zeros((cap, 3), np.float32)
        self._t = np.zeros(cap if self._need_t else 1, np.float64)
        self._imp = np.zeros(cap if self._need_imp else 1, np.float32)
        self._cval = np.zeros(1, np.float32)   # the scalar colour channel (scalar mode; sized in _sync)
        self._rgb = np.zeros(1, np.uint32)     # packed rgb (rgb mode; sized in _sync)
        self._cmode_chan: Optional[str] = None
        self._origin = None
        self._batches(cap)

    def _batches(self, cap: int) -> None:
        """Bounds per batch of BIN_CHUNK slots of the own copy (kept as it is written: only
        the batches of the dirty ranges are reduced again, when a frame needs them)."""
        nbat = -(-cap // BIN_CHUNK)
        if getattr(self, "_bstale", np.zeros(0)).shape[0] != nbat:
            self._blo, self._bhi = np.zeros((nbat, 3)), np.zeros((nbat, 3))
            self._bbad, self._bvlo, self._bvhi = np.zeros(nbat, np.int64), np.zeros(nbat), np.zeros(nbat)
            self._bstale = np.ones(nbat, bool)

    def _lod_masks(self, frame: FrameInput, camera: Camera, cmode: int) -> np.ndarray:
        """The footprint LOD's mask per batch (batches.lod_masks) from the copy's own batch
        bounds, every batch reduced; empty when ``render.lod_fill`` is off."""
        if not self.cfg.lod_fill > 0:
            return _NO_LOD
        cap = self._cap
        self._batches(cap)
        stale = np.flatnonzero(self._bstale)
        if stale.size:
            self._k.batch_stats(stale.astype(np.int64), BIN_CHUNK, cap, self._pos, self._t, self._cval, cmode,
                                self._blo, self._bhi, self._bbad, self._bvlo, self._bvhi)
            self._bstale[stale] = False
        masks = frame_lod_masks(self._blo, self._bhi, frame, camera, self.cfg, self.width, self.height, BIN_CHUNK)
        return masks if masks.any() else _NO_LOD  # (nothing thinned: the loops skip the test)

    def _lod_counted(self, blod: np.ndarray, head: int, size: int, cap: int, chunks,
                     range_mode: int) -> tuple[np.ndarray, int, Optional[tuple[float, float]]]:
        """Flag :data:`~pointflow.render.batches.LOD_CPU_COUNTED` on the thinned batches whose
        slots are all occupied (and, split by bins, that are not culled): their non-finite
        count and colour range are the batch bounds' (:meth:`_lod_masks` reduced every batch),
        so the raster loops never read their dropped slots. Returns (the mask words, the
        flagged batches' non-finite count, their colour range or None)."""
        B = BIN_CHUNK
        flag = lod_countable(blod, head, size, cap, B)
        if chunks is not None:  # culled chunks count their batch themselves
            ca, _, culled = chunks[0], chunks[1], chunks[2]
            flag[((ca[culled == 1] + head) % cap) // B] = False
        ks = np.flatnonzero(flag)
        if not ks.size:
            return blod, 0, None
        words = blod.copy()
        words[ks] |= np.uint32(LOD_CPU_COUNTED)
        vr = (float(self._bvlo[ks].min()), float(self._bvhi[ks].max())) if range_mode else None
        return words, int(self._bbad[ks].sum()), vr

    def _colour_mode(self, frame: FrameInput) -> tuple[int, Optional[str]]:
        cb = self.cfg.color_by
        if cb in (None, "none"):
            return cpu_kernels.C_SINGLE, None
        if cb == "rgb":
            return (cpu_kernels.C_RGB, "rgb") if "rgb" in frame.channels else (cpu_kernels.C_SINGLE, None)
        if cb in ("z", "height"):
            return cpu_kernels.C_Z, None
        if cb == "ingest_time":
            return cpu_kernels.C_TIME, None
        ch = frame.channels.get(cb)
        if ch is None or ch.ndim != 1:
            return cpu_kernels.C_SINGLE, None
        return cpu_kernels.C_SCALAR, cb

    def _sync(self, frame: FrameInput, cmode: int, chan: Optional[str]) -> int:
        """Copy the dirty ranges (all of them after an origin, capacity or colour change);
        returns the bytes copied."""
        cap = int(frame.capacity)
        if cap != self._cap:
            self._alloc(cap)
        origin = np.asarray(frame.origin, np.float64)
        full = (frame.dirty is None or self._origin is None or not np.array_equal(origin, self._origin)
                or (cmode, chan) != getattr(self, "_synced_mode", None))
        if cmode == cpu_kernels.C_SCALAR and self._cval.shape[0] != cap:
            self._cval, full = np.zeros(cap, np.float32), True
        if cmode == cpu_kernels.C_RGB and self._rgb.shape[0] != cap:
            self._rgb, full = np.zeros(cap, np.uint32), True
        ranges = [(0, cap)] if full else merge_ranges(list(frame.dirty or []), cap)
        total = 0
        for a, b in ranges:
            self._bstale[a // BIN_CHUNK:-(-b // BIN_CHUNK)] = True
            self._pos[a:b] = frame.positions[a:b]
            total += (b - a) * 12
            if self._need_t:
                self._t[a:b] = frame.t_ingest_ms[a:b]
                total += (b - a) * 8
            if self._need_imp:
                self._imp[a:b] = frame.importance[a:b]
                total += (b - a) * 4
            if cmode == cpu_kernels.C_SCALAR:
                self._cval[a:b] = frame.channels[chan][a:b]
                total += (b - a) * 4
            elif cmode == cpu_kernels.C_RGB:
                rgb = np.asarray(frame.channels["rgb"][a:b], np.uint32)
                self._rgb[a:b] = rgb[:, 0] | (rgb[:, 1] << 8) | (rgb[:, 2] << 16) | np.uint32(0xFF000000)
                total += (b - a) * 4
        self._origin = origin.copy()
        self._synced_mode = (cmode, chan)
        return total

    def _rule(self, T: int) -> str:
        """The split without measurements: the forced one, else points for at most
        POINTS_UP_TO_THREADS threads, bins for more."""
        if self.split_mode != "auto":
            return self.split_mode
        return "points" if T <= POINTS_UP_TO_THREADS else "bins"

    def _pick(self) -> tuple[str, int]:
        """This frame's (split, thread count): every thread numba has (``numba.get_num_threads()``)
        or one, and with ``auto`` the bins or the points split, whichever drew faster lately
        (the image is the same either way). The first frames try each in turn (all threads
        first, bins first); then the fastest draws, and every RETRY_EVERY frames one of the
        others is re-tried in rotation, so a machine whose other load changes is followed."""
        most = max(1, int(self._k_numba().get_num_threads()))
        if most == 1 or not self._adaptive:
            return self._rule(most), most
        splits = ("bins", "points") if self.split_mode == "auto" else (self.split_mode,)
        cands = [(sp, t) for t in (most, 1) for sp in splits]
        for c in cands:
            if len(self._tune.get(c, [])) < TUNE_FRAMES:
                return c
        ranked = sorted(cands, key=lambda c: float(np.median(self._tune[c])))
        self._tune_n += 1
        if self._tune_n % RETRY_EVERY == 0:
            return ranked[1 + (self._tune_n // RETRY_EVERY) % (len(ranked) - 1)]
        return ranked[0]

    @staticmethod
    def _tiles(W: int, H: int) -> np.ndarray:
        """A flag per tile of a W x H target (cpu_kernels.TILE_XS/TILE_YS), all set."""
        TW, TH = cpu_kernels.tile_grid(W, H)
        return np.ones(TW * TH, np.uint8)

    def _buffers(self, threads: Optional[int] = None) -> np.ndarray:
        """The key buffers for this frame's thread count: one (bands) or one per thread, with
        their tile marks (a row per thread numba may run: the bands split's threads mark rows
        that are not buffers; new buffers are marked whole, so their first frame clears them)."""
        self.threads = T = max(1, int(self._k_numba().get_num_threads())) if threads is None else threads
        nb = 1 if self.bands else T
        # grown, never shrunk: a frame at another thread count takes the first rows (reallocating
        # here cost page faults over every buffer each time the count changed)
        if self._keys.base is None or self._keys.base.shape[0] < nb or self._keys.shape[1] != self.width * self.height:
            self._keys = np.empty((max(nb, self._keys.shape[0]), self.width * self.height), np.uint64)[:nb]
            rows = max(self._keys.base.shape[0], int(cpu_kernels.numba.config.NUMBA_NUM_THREADS))
            self._marks = np.ones((rows, self._tiles(self.width, self.height).shape[0]), np.uint8)
        else:
            self._keys = self._keys.base[:nb]
        return self._keys

    @staticmethod
    def _k_numba():
        return cpu_kernels.numba

    def _warm(self) -> None:
        """Compile (or load from the disk cache) every loop now, not on the first frame."""
        cap = 4
        f = FrameInput(positions=np.zeros((cap, 3), np.float32), importance=np.zeros(cap, np.float32),
                       t_ingest_ms=np.zeros(cap), channels={}, head=0, size=cap, capacity=cap,
                       origin=np.zeros(3), now_ms=0.0, budget=1)
        cam = Camera(eye=[0, -5, 0], target=[0, 0, 0], near=0.1, far=100)
        saved = (self._cap, self._pos, self._t, self._imp, self._cval, self._rgb, self._origin, self.split_mode)
        try:
            for mode in (("points", "bins") if self.split_mode == "auto" else (self.split_mode,)):
                self.split_mode = mode  # auto draws with both
                self.render(f, cam)
                self.winners(0, 1, 0, 1)  # the pick (keys of a few rows)
            one = np.zeros((1, 3))  # the batch bounds (culling: not reached by the frames above)
            self._k.batch_stats(np.zeros(1, np.int64), BIN_CHUNK, cap, f.positions, np.zeros(1), np.zeros(1, np.float32),
                                cpu_kernels.C_SINGLE, one, one.copy(), np.zeros(1, np.int64), np.zeros(1), np.zeros(1))
            # the one-thread resolve (not reached by the frames above, drawn with every thread)
            empty = np.full((1, self.width * self.height), cpu_kernels.EMPTY, np.uint64)
            self._k.resolve_1(empty, self._tiles(self.width, self.height)[None], self._shown, self._img, self._logz,
                              self._edl is not None, np.eye(4), 0, cap, cpu_kernels.C_SCALAR, self._single, self._bg,
                              self._rgb, f.positions, np.zeros(cap), np.zeros(cap, np.float32), np.float32(0),
                              np.float32(1), False, self._lut)
        finally:
            self._cap, self._pos, self._t, self._imp, self._cval, self._rgb, self._origin, self.split_mode = saved
            self._img[:] = self._bg
            self._shown[:] = 1
            self._keys[:] = cpu_kernels.EMPTY
            self._marks[:] = 1  # every tile of every buffer (rows beyond these too) cleared by its next frame
            self._bins, self._drew = _Bins(), False
            self._synced_mode = None
            self.frames = 0
            self.nonfinite_total = 0
            self._tune, self._tune_n, self.frames_at, self.frames_by = {}, 0, {}, {}

    # ---------------------------------------------------------------- binned raster
    def _chunks(self, head: int, size: int, cap: int, cmode: int, planes: np.ndarray, cull: bool):
        """The binning pass's chunks: the occupied logical range cut at the ring's end and at
        every batch of BIN_CHUNK slots, as (first, end) logical indices; per chunk whether it
        is a whole batch whose bounds lie wholly outside one frustum plane (culled: no point is
        touched), with that batch's non-finite count and colour value range."""
        B = BIN_CHUNK
        runs = [(head, 0, min(size, cap - head))]
        if head + size > cap:
            runs.append((0, cap - head, head + size - cap))
        starts, lens = [], []
        for s0, l0, n in runs:
            cut = np.arange(-(-s0 // B) * B, s0 + n, B)
            edges = np.unique(np.concatenate([[s0], cut, [s0 + n]]))
            starts.append(edges[:-1])
            lens.append(np.diff(edges))
        s = np.concatenate(starts) if starts else np.zeros(0, np.int64)
        n = np.concatenate(lens) if lens else np.zeros(0, np.int64)
        ca = ((s - head) % cap).astype(np.int64)
        cb = ca + n
        k = s // B
        C = len(ca)
        flag = np.zeros(C, np.uint8)
        cbad = np.zeros(C, np.int64)
        cvr = np.zeros((C, 2))
        if cull and C:
            self._batches(cap)
            whole = (s == k * B) & (n == np.minimum((k + 1) * B, cap) - k * B)
            kw = np.unique(k[whole])
            stale = kw[self._bstale[kw]]
            if stale.size:
                self._k.batch_stats(stale.astype(np.int64), B, cap, self._pos, self._t, self._cval, cmode, self._blo,
                                    self._bhi, self._bbad, self._bvlo, self._bvhi)
                self._bstale[stale] = False
            out = boxes_outside(self._blo[k], self._bhi[k], planes)  # one plane test for every tier
            empty = self._bbad[k] == n  # no finite point at all
            sel = whole & (out | empty)
            flag[sel] = 1
            cbad[sel] = self._bbad[k[sel]]
            cvr[sel, 0], cvr[sel, 1] = self._bvlo[k[sel]], self._bvhi[k[sel]]
        return ca, cb, flag, cbad, cvr

    def _bin_pass(self, chunks, st, vr, mask, use_mask, head, size, cap, vp, planes, half, world, size_scale, round_,
                  has_window, now, window, lod, blod, has_imp, imp_deg, imp_lo, imp_scale, seed_h, range_mode,
                  eps_s) -> None:
        """Pass 1 (rules, projection, boxes, records sorted by band); run again with larger
        chunk regions when a chunk needed more records than its region holds."""
        bn, W, H = self._bins, self.width, self.height
        nt = max(1, int(cpu_kernels.numba.config.NUMBA_NUM_THREADS))
        if len(self._bin_scratch) == 0 or self._bin_scratch[0].shape[0] < nt or \
                self._bin_scratch[3].shape[1] != -(-H // bn.BH) + 2 or (round_ and self._bin_scratch[2].shape[1] == 1):
            self._bin_scratch = (np.empty((nt, BIN_CHUNK), np.uint64), np.empty((nt, BIN_CHUNK), np.uint64),
                                 np.empty((nt, BIN_CHUNK if round_ else 1, 3), np.float64),
                                 np.zeros((nt, -(-H // bn.BH) + 2), np.int64))
        sk, sb, sf, scur = self._bin_scratch
        ca, cb, cull, cbad, cvr = chunks
        C = len(ca)
        need = np.zeros(C, np.int64)
        for _ in range(2):
            bn.ready(C, int(np.ceil(BIN_CHUNK * self._records_per_point)), round_, H)
            self._k.bin(bn.rkey, bn.rbox, bn.rf, bn.off, need, st, vr, ca, cb, cull, cbad, cvr, mask, use_mask, sk, sb,
                        sf, scur, self._pos,
                        self._t, self._imp, self._cval, head, size, cap, W, H, vp, planes, half, world, size_scale,
                        round_, has_window, now, window, lod, blod, has_imp, imp_deg, imp_lo, imp_scale, seed_h,
                        range_mode, eps_s, BIN_CHUNK, bn.RC, bn.BS, bn.NB)
            most = int(need.max()) if C else 0
            if most <= bn.RC:
                return
            self._records_per_point = most / BIN_CHUNK * 1.0625  # then run the pass again
        raise RenderError(f"cpu compute raster: binning needed {most} records per chunk after growing")

    def _band_buffers(self) -> np.ndarray:
        """One band of keys per thread (BH rows: stays in the core's cache)."""
        nt = max(1, int(cpu_kernels.numba.config.NUMBA_NUM_THREADS))
        n = self._bins.BH * self.width
        kb = getattr(self, "_kbuf", None)
        if kb is None or kb.shape != (nt, n):
            kb = self._kbuf = np.empty((nt, n), np.uint64)
        return kb

    # ---------------------------------------------------------------- render
    def render(self, frame: FrameInput, camera: Camera) -> FrameStats:
        nb = self._k_numba()
        caller = nb.get_num_threads()
        split, T = self._pick()
        nb.set_num_threads(T)
        try:
            st = self._render(frame, camera, T, split)
        except (ValueError, RenderError):  # a malformed frame (skipped, counted), or already a tier failure
            raise
        except Exception as exc:  # noqa: BLE001 - the render stage falls back only on RenderError
            raise RenderError(f"cpu compute raster failed: {type(exc).__name__}: {exc}") from exc
        finally:
            nb.set_num_threads(caller)
        self.frames_at[T] = self.frames_at.get(T, 0) + 1
        self.frames_by[(split, T)] = self.frames_by.get((split, T), 0) + 1
        if self._adaptive and caller > 1:
            ts = self._tune.setdefault((split, T), [])
            ts.append(st.timings_ms["total"])
            del ts[:-TUNE_FRAMES]
        return st

    def _render(self, frame: FrameInput, camera: Camera, T: int, split: str) -> FrameStats:
        cap, size = check_frame(frame)
        if not 0 <= int(frame.head) < cap:
            raise ValueError(f"FrameInput.head must be in 0..capacity-1 ({cap - 1}), got {frame.head}")
        t0 = time.perf_counter()
        cfg, W, H, k = self.cfg, self.width, self.height, self._k
        cmode, chan = self._colour_mode(frame)
        copied = self._sync(frame, cmode, chan)
        t1 = time.perf_counter()
        head = int(frame.head)
        origin = np.asarray(frame.origin, np.float64)
        vp = np.ascontiguousarray(camera.view_proj(W, H, origin), np.float64)
        planes = np.ascontiguousarray(planes_of(vp), np.float64).reshape(6, 4)  # frustum_planes, one matrix
        # clip-space frustum decisions need a margin far above float64 rounding of a dot
        # product with these coefficients (|error| <= ~4e-16 * sum |terms|); the planes decide
        # the points inside the margin (cpu_kernels._frustum)
        eps_s = 1e-11 * 2.0 * float(np.abs(vp).max())
        world = cfg.point_size_space == "world"
        size_scale = float(cfg.point_size) * float(camera.proj(W, H)[1, 1]) * H * 0.5 if world else 0.0
        # importance sampling: the handoff's range, else the finite range over occupied slots
        has_imp, imp_deg, imp_lo, imp_scale = bool(cfg.importance_sampling), True, np.float32(0), np.float32(0)
        if has_imp:
            r = frame.channel_ranges.get("importance")
            if r is None:
                occ = frame.occupied_slots()
                v = self._imp[occ]
                v = v[np.isfinite(v)]
                r = (float(v.min()), float(v.max())) if v.size else (0.0, 0.0)
            lo, hi = float(r[0]), float(r[1])
            if hi > lo:
                imp_deg, imp_lo, imp_scale = False, np.float32(lo), np.float32(1.0 / (hi - lo))
        # colour range: fixed, the handoff's, or reduced in the raster pass (auto)
        shift = float(frame.origin[2]) if cmode == cpu_kernels.C_Z else 0.0
        range_mode, lo_c, hi_c = 0, 0.0, 0.0
        if cmode in (cpu_kernels.C_SCALAR, cpu_kernels.C_Z, cpu_kernels.C_TIME):
            if isinstance(cfg.color_range, list):
                lo_c, hi_c = float(cfg.color_range[0]) - shift, float(cfg.color_range[1]) - shift
            elif cmode == cpu_kernels.C_SCALAR and chan in frame.channel_ranges:
                lo_c, hi_c = (float(x) for x in frame.channel_ranges[chan])
            else:
                range_mode = cmode
        self.threads, self.split = T, split
        bins = self.split == "bins"
        keys = self._buffers(T) if not bins else self._keys
        if bins:  # culling needs the tests of every point done here (not by the budget's passes)
            chunks = self._chunks(head, size, cap, cmode, planes, self._cull and not use_mask_of(frame, size))
            C = max(1, len(chunks[0]))
            self.culled_points = int((chunks[1] - chunks[0])[chunks[2] == 1].sum())
        else:
            C = T if self.bands else T * CHUNKS_PER_THREAD  # chunks of the raster pass
        st = np.zeros((max(C, T), cpu_kernels.N_ST), np.int64)
        vr = np.empty((max(C, T), 2), np.float64)
        vr[:, 0], vr[:, 1] = np.inf, -np.inf
        seed_h = np.uint64(seed_hash(frame.frame_seed))
        has_window = cfg.time_window_ms > 0
        now, window = float(frame.now_ms), float(cfg.time_window_ms)
        lod = max(int(cfg.lod_stride), 1)
        blod = self._lod_masks(frame, camera, cmode)
        half = float(cfg.point_size) * 0.5
        round_ = cfg.point_shape == "round"
        use_mask = use_mask_of(frame, size)
        mask = np.zeros(size if use_mask else 1, np.uint8)
        lod_bad, lod_vr = 0, None
        if blod.size and not use_mask:  # (the budget's passes count every slot themselves)
            blod, lod_bad, lod_vr = self._lod_counted(blod, head, size, cap, chunks if bins else None, range_mode)
        counts = {"occupied": size}
        if use_mask:  # budget: tests -> thinning -> the first b in logical order
            b = max(int(frame.budget), 0)
            k.select(mask, st, vr, self._pos, self._t, self._imp, self._cval, head, size, cap, T, vp, planes,
                     has_window, now, window, lod, blod, has_imp, imp_deg, imp_lo, imp_scale, seed_h, range_mode, eps_s)
            n = int(st[:, cpu_kernels.ST_KEEP].sum())
            if n > b:
                per = np.zeros(T, np.int64)
                k.thin(mask, per, head, size, cap, T, np.uint64(budget_seed(frame.frame_seed)),
                       np.float32(budget_fraction(b, n)))
                base = np.concatenate([[0], np.cumsum(per)[:-1]]).astype(np.int64)
                k.cap(mask, base, size, T, b)
            pre = st.copy()
            pre_vr = vr.copy()
        t2 = time.perf_counter()
        nb = self._k_numba()
        prev = nb.set_parallel_chunksize(1)  # chunks go to whichever thread is free
        try:
            if bins:
                self._bin_pass(chunks, st, vr, mask, use_mask, head, size, cap, vp, planes, half, world, size_scale,
                               round_, has_window, now, window, lod, blod, has_imp, imp_deg, imp_lo, imp_scale, seed_h,
                               range_mode, eps_s)
            else:
                k.raster(keys, self._marks, T, C, self.bands, st, vr, mask, use_mask, self._pos, self._t, self._imp, self._cval,
                         head, size, cap, W, H, vp, planes, half, world, size_scale, round_, has_window, now, window,
                         lod, blod, has_imp, imp_deg, imp_lo, imp_scale, seed_h, range_mode, eps_s)
        finally:
            nb.set_parallel_chunksize(prev)
        if self.bands:  # one buffer, written by every thread: the resolve reads all of it
            self._marks[0] = 1
        t3 = time.perf_counter()
        drawn = int(st[:, cpu_kernels.ST_DRAWN].sum())
        if use_mask:
            st, vr = pre, pre_vr
        nonfinite = int(st[:, cpu_kernels.ST_BAD].sum()) + lod_bad
        if range_mode:
            mn, mx = float(vr[:, 0].min()), float(vr[:, 1].max())
            if lod_vr is not None:
                mn, mx = min(mn, lod_vr[0]), max(mx, lod_vr[1])
            if mn > mx:
                mn = mx = 0.0
            lo_c, hi_c = (mn + shift) - shift, (mx + shift) - shift
        degenerate = not hi_c > lo_c
        lo32 = np.float32(lo_c)
        scale32 = np.float32(1.0 / (hi_c - lo_c)) if not degenerate else np.float32(0)
        self._last_ring = (head, cap)
        self._drew = True
        if bins:  # keys per band and the resolve in one pass
            bn = self._bins
            prev = nb.set_parallel_chunksize(1)
            try:
                k.bands(self._band_buffers(), self._img, self._logz, self._edl is not None, bn.rkey, bn.rbox, bn.rf,
                        bn.off, W, H, bn.BS, bn.NB, round_, vp, head, cap, cmode, self._single, self._bg, self._rgb,
                        self._pos, self._t, self._cval, lo32, scale32, degenerate, self._lut)
            finally:
                nb.set_parallel_chunksize(prev)
            self._shown[:] = 1  # every pixel written
        elif T == 1:  # the same rule; one thread: the serial build
            k.resolve_1(keys, self._marks, self._shown, self._img, self._logz, self._edl is not None, vp, head, cap,
                        cmode, self._single, self._bg, self._rgb, self._pos, self._t, self._cval, lo32, scale32,
                        degenerate, self._lut)
        else:
            prev = nb.set_parallel_chunksize(1)  # rows of tiles as threads come free: the drawn ones cluster
            try:
                k.resolve(keys, self._marks, self._shown, self._img, self._logz, self._edl is not None, vp, head, cap,
                          cmode, self._single, self._bg, self._rgb, self._pos, self._t, self._cval, lo32, scale32,
                          degenerate, self._lut)
            finally:
                nb.set_parallel_chunksize(prev)
        t4 = time.perf_counter()
        if self._edl is not None:
            k.edl(self._logz, self._img, self._edl, -EDL_SCALE * float(cfg.edl.strength))
        t5 = time.perf_counter()
        self.nonfinite_total += nonfinite
        self.frames += 1
        counts["nonfinite"] = nonfinite
        ms = lambda a, b: (b - a) * 1e3
        timings = {"copy": ms(t0, t1), "select": ms(t1, t2), "raster": ms(t2, t3), "resolve": ms(t3, t4),
                   "total": ms(t0, t5)}
        if self._edl is not None:
            timings["edl"] = ms(t4, t5)
        return FrameStats(drawn=drawn, timings_ms=timings, uploaded_bytes=copied,
                          extra={"removed_nonfinite": nonfinite, "nonfinite_total": self.nonfinite_total,
                                 "occupied": size, "threads": T, "raster": "compute",
                                 "split": self.split, "culled_points": self.culled_points if bins else 0,
                                 "lod_cpu_counted_batches": int(np.count_nonzero(blod & np.uint32(LOD_CPU_COUNTED)))})

    def resize(self, width: int, height: int) -> bool:
        """A target per size (image, EDL depth, key buffers), kept for switching back; the
        ring copy is shared, so a view of another size uploads nothing."""
        size = (int(width), int(height))
        if size == (self.width, self.height):
            return True
        targets = self.__dict__.setdefault("_targets", {})
        # the binned records are one buffer for every size (they scale with the ring, not the
        # view): a size whose last frame was binned answers picks again once it has drawn
        targets[(self.width, self.height)] = (self._img, self._shown, self._logz, self._keys, self._marks,
                                              self._last_ring, self._drew and self.split != "bins", self.split)
        if size in targets:
            (self._img, self._shown, self._logz, self._keys, self._marks, self._last_ring, self._drew,
             self.split) = targets[size]
        else:
            W, H = size
            self._img = np.empty((H, W), np.uint32)
            self._img[:] = self._bg
            self._shown = self._tiles(W, H)
            self._marks = np.ones((0, 1), np.uint8)
            self._logz = np.zeros(H * W if self._edl is not None else 1, np.float64)
            self._keys, self._last_ring = np.empty((0, H * W), np.uint64), (0, 1)
            self._drew = False
        self.width, self.height = size
        return True

    # ---------------------------------------------------------------- outputs
    def read_image(self) -> np.ndarray:
        return self._img.view(np.uint8).reshape(self.height, self.width, 4).copy()

    def winners(self, ya: int = 0, yb: Optional[int] = None, xa: int = 0, xb: Optional[int] = None) -> np.ndarray:
        """Ring slot drawn at each pixel of the last frame's block [ya:yb, xa:xb] (-1 =
        background), from the key buffers (the smallest key over the threads' buffers)."""
        H, W = self.height, self.width
        if self.split == "bins":
            ya, yb = range(H)[slice(ya, yb)].start, range(H)[slice(ya, yb)].stop
            bn = self._bins
            out = np.empty(max(yb - ya, 0) * W, np.uint64)
            if yb > ya:
                self._k.keys_rows(out, np.empty(bn.BH * W, np.uint64), ya, yb, bn.rkey, bn.rbox, bn.rf, bn.off, W,
                                  H, bn.BS, bn.NB,
                                  self.cfg.point_shape == "round")
            kb = out.reshape(yb - ya, W)[:, xa:xb]
        else:
            kb = self._keys.reshape(-1, H, W)[:, ya:yb, xa:xb].min(axis=0)
        head, cap = self._last_ring
        slots = ((kb & np.uint64(0xFFFFFFFF)).astype(np.int64) + head) % cap
        return np.where(kb == cpu_kernels.EMPTY, -1, slots)

    def pick(self, x: float, y: float, pixel_ratio: float = 1.0) -> Optional[int]:
        win = pick_window(self.width, self.height, x, y, pixel_ratio, self.cfg.pick_radius)
        if win is None or not self._drew:
            return None
        X, Y, xa, xb, ya, yb = win
        block = self.winners(ya, yb, xa, xb)
        block = in_pick_circle(block, xa, ya, x, y, pixel_ratio, self.cfg.pick_radius)
        last: dict[str, np.ndarray] = {}
        if self.cfg.pick_strategy != "nearest":  # attributes of the last frame's own copy
            s = np.unique(block[block >= 0])
            last = {"slots": s, "importance": self._imp[s].astype(np.float64) if self._need_imp else np.zeros(s.size),
                    "t": self._t[s].astype(np.float64) if self._need_t else np.zeros(s.size)}
        return resolve_pick(block, X - xa, Y - ya, self.cfg.pick_strategy, last)

    def info(self) -> dict[str, Any]:
        return {"tier": self.tier, "raster": self.raster, "size": [self.width, self.height],
                "split": self.split, "split_mode": self.split_mode, "adaptive_threads": self._adaptive,
                "frames_per_thread_count": {str(t): n for t, n in sorted(self.frames_at.items())},
                "frames_per_split_and_threads": {f"{sp}/{t}": n for (sp, t), n in sorted(self.frames_by.items())},
                "threads": int(cpu_kernels.numba.get_num_threads()), "numba": cpu_kernels.numba.__version__,
                "deterministic": True}


#: the compile-ahead target (``python -m pointflow.jitcache``, ``pointflow warm``)
COMPILE_TARGET = "pointflow.render.cpu_compute:compile_all"


def compile_all(dispatchers_only: bool = False) -> list:
    """Compile every loop a render stage runs (a renderer with eye-dome lighting draws its
    warm-up frame: every kernel of :data:`cpu_kernels.REQUIRED`) into numba's disk cache;
    returns the dispatchers. ``dispatchers_only``: compile nothing, only return them."""
    if not dispatchers_only and cpu_kernels.load() is not None:
        from .config import EdlConfig

        CpuComputeRenderer(RenderConfig(size=[64, 36], edl=EdlConfig(enabled=True)), 16, ["intensity"]).close()
    return cpu_kernels.dispatchers()
