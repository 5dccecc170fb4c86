"""The wgpu render tier's core: device, incremental upload, Params, counters, timing, picking.

The raster method (``render.raster``) is a strategy (:mod:`.raster`): the core owns what
every method shares and hands it over as a :class:`.raster.Gpu`; the method records its
passes for each frame's :class:`.raster.FramePlan`. Frame path (no Python loop over points,
no readback on the frame path):

1. upload the dirty slot ranges (:mod:`.upload`) into the point buffers (one set, :data:`DATA_SETS`:
   ``queue.write_buffer`` lands after every frame submitted before it, so a frame in flight
   still reads its own points);
2. write the frame's ``Params`` (:mod:`.frame_params`) and reset the counters;
3. the method's passes (quads: cull + compaction + indirect draw; compute: fused tests +
   atomic depth keys + per-pixel resolve);
4. copy the counters into a fence buffer and submit.

A ring larger than one storage binding is kept in chunks of slots, each with its own buffers,
and every pass runs once per segment of the ring (:mod:`.chunks`): every slot is drawn.

Batch culling (:mod:`.culling`): the passes over points walk only the runs of the ring
between whole batches culled on the CPU; counters and the automatic colour range are those
without culling.

Compact positions (:mod:`.compact`): per batch 4, 8 or 12 B of position per point.

At most two frames are in flight: before frame ``k`` we wait for frame ``k - 2`` (its
fence ``k % 2``), which bounds latency when the GPU is slower than the cadence.
The wait maps a 64-byte fence into which that frame copied its counters, so the
``FrameStats`` of a frame gets ``drawn`` / ``removed_nonfinite`` two frames later (or at
``read_image()``, which waits for the GPU anyway) without ever stalling for them.
"""
from __future__ import annotations

import copy
import logging
import time
from typing import Any, Optional

import numpy as np

from ..config import RenderConfig
from .. import batches, colormap
from ..base import FrameInput, FrameStats, Range, Renderer, RenderError, merge_ranges
from ..batches import BatchBounds
from ..camera import Camera
from . import chunks, frame_params
from .device import adapter_summary, request_device, select_adapter
from .layout import PARAMS_DTYPE, ColourMode, Flag
from .compact import CompactPositions, compact_choice
from .culling import CPU_COUNTED, Culling
from .pick import pick_block, resolve_pick
from .upload import IncrementalUpload
from .raster import METHODS, FramePlan, Gpu, RasterMethod, choose_raster

log = logging.getLogger("pointflow.render.wgpu")

_MAX_GROUPS = 65535

#: Sets of point buffers. One: WebGPU orders ``queue.write_buffer`` on the queue's timeline
#: after every earlier submission, so the upload for frame k + 1 cannot reach a buffer frame k
#: still reads (tested: tests/render_tiers/test_frame_reuse.py). Two sets, alternating, also
#: drew correctly, but each set caught up on the ranges it had missed: every range was
#: uploaded twice, and the points took twice the GPU memory.
DATA_SETS = 1

#: test-only switch: draw with an absolute float32 model matrix instead of the float64
#: origin-relative view-projection (shows the large-coordinate error it avoids).
NAIVE_FLOAT32 = False


__all__ = ["WgpuRenderer", "merge_ranges", "resolve_pick"]


class WgpuRenderer(IncrementalUpload, Renderer):
    """GPU tier on wgpu. ``info()`` reports the adapter, limits, caps and timestamp support."""

    tier = "wgpu"
    keeps_data = True

    def __init__(self, cfg: RenderConfig, capacity: int, channels: list[str], *,
                 adapter: Any = None, naive_float32: Optional[bool] = None,
                 key64: Optional[bool] = None, max_groups: Optional[int] = None,
                 max_binding: Optional[int] = None):
        super().__init__(cfg, capacity, channels)
        import wgpu
        self._wgpu = wgpu
        self.naive_float32 = NAIVE_FLOAT32 if naive_float32 is None else bool(naive_float32)
        if self.width < 1 or self.height < 1:
            raise RenderError(f"render.size must be positive, got {cfg.size}")
        why = "given by caller"
        if adapter is None:
            adapter, why = select_adapter(cfg.power_preference)
            if adapter is None:
                raise RenderError(f"wgpu tier unavailable: {why}")
        lim = adapter.limits
        try:
            self.raster, self._raster_why = choose_raster(
                cfg, adapter.features, self.width * self.height * 8,
                int(min(lim.get("max-storage-buffer-binding-size", 2 ** 27), lim.get("max-buffer-size", 2 ** 28))),
                int(capacity))
        except ValueError as e:
            raise RenderError(str(e)) from e
        self._method_cls: type[RasterMethod] = METHODS[self.raster]
        try:
            self.device, dinfo = request_device(adapter, bool(cfg.gpu_timestamps),
                                                self._method_cls.wanted_features(cfg, key64))
        except Exception as e:
            raise RenderError(f"wgpu device request failed on {adapter.summary}: {e}") from e
        self.adapter = adapter
        self._adapter_why = why
        self.queue = self.device.queue
        self._ts = dinfo["timestamps"]
        self._limits = dinfo["limits"]
        self._key64 = bool(dinfo["features"])
        self._max_groups = int(max_groups or self._limits.get("max-compute-workgroups-per-dimension", _MAX_GROUPS))
        self._caps: list[str] = []
        self._max_binding = max_binding  # tests: a smaller storage-binding limit (more chunks)
        self.render_capacity = max(int(capacity), 1)
        self._chunk_table = self._chunk_plan(self.render_capacity)
        self._nseg = 1 if len(self._chunk_table) == 1 else len(self._chunk_table) + 1
        self._cut = [(0, 0), (0, 0)]  # per fence: (non-finite, occupied) of slots the passes skip
        self._setup_colour(channels)
        self._bounds = BatchBounds(batches.BATCH_SLOTS)  # culling's and the compact positions'
        # the footprint LOD's: the shaders find a slot's batch by a shift of BATCH_SHIFT (tests
        # that shrink BATCH_SLOTS get a second BatchBounds of the shaders' batches)
        self._lod_bounds = self._bounds if self._bounds.batch == 1 << batches.BATCH_SHIFT else \
            BatchBounds(1 << batches.BATCH_SHIFT)
        self._culling = Culling(self._cmode, self._cchan, self._bounds) if batches.culling_enabled() else None
        self._compact_on, self._compact_why = compact_choice(adapter.info.get("adapter_type", ""), self.raster,
                                                             self.naive_float32)
        self._compact: Optional[CompactPositions] = None
        if self._culling is not None:  # Params/state windows: the segments, then their runs
            self._nseg = 2 * self._nseg + -(-self.render_capacity // self._culling.bounds.batch)
        self._need_t = cfg.time_window_ms > 0 or self._cmode == ColourMode.TIME or cfg.pick_strategy == "recent_first"
        self._need_imp = bool(cfg.importance_sampling) or cfg.pick_strategy == "highest_importance"
        self._method: Optional[RasterMethod] = None
        try:
            self._create_resources()
        except Exception as e:
            raise RenderError(f"wgpu tier setup failed: {type(e).__name__}: {e}") from e
        self._pending: list[list[Range]] = [[(0, self.render_capacity)] for _ in range(DATA_SETS)]
        self._done = [False, False]
        self._stats: list[Optional[FrameStats]] = [None, None]
        self.nonfinite_total = 0
        self._ts_used = [False, False]
        self._frame_no = 0
        self._last: Optional[FramePlan] = None
        self._last_fence = 0  # the fence of the last frame
        self._origin: Optional[np.ndarray] = None
        self._gpu_ms: dict[str, float] = {}
        self._view_cache = frame_params.ViewCache()
        self._closed = False
        self._compact_force = -1  # tests: one level for every batch
        log.info("wgpu tier on %s (%s); capacity %d%s; timestamps %s", adapter.summary, why,
                 self.render_capacity, f" in {len(self._chunk_table)} chunks of up to "
                 f"{self._chunk_table[0][1]} slots ({self._chunk_why})" if len(self._chunk_table) > 1 else "",
                 "on" if self._ts else "off")
        log.info("wgpu tier raster method: %s (%s)%s", self.raster, self._raster_why,
                 "".join(f"; {k}: {v}" for k, v in self._method.info().items()))

    # ------------------------------------------------------------------ setup
    def _chunk_plan(self, capacity: int) -> list[tuple[int, int]]:
        """The ring's chunks (:mod:`.chunks`): as many slots per chunk as the method's widest
        per-slot array fits in one storage binding (and one buffer) and one dispatch."""
        lim = self._limits
        per_binding = int(lim.get("max-storage-buffer-binding-size", 2 ** 27))
        per_buffer = int(lim.get("max-buffer-size", 2 ** 28))
        limit = min(per_binding, per_buffer, int(self._max_binding or per_binding))
        groups = int(lim.get("max-compute-workgroups-per-dimension", _MAX_GROUPS))
        m = self._method_cls
        clen = chunks.chunk_len(limit, m.slot_bytes, m.pad_slots, groups * groups * m.points_per_group)
        if clen < chunks.ALIGN_SLOTS:
            raise RenderError(f"wgpu tier: a storage binding of {limit} bytes cannot hold "
                              f"{chunks.ALIGN_SLOTS} points of the {m.name} method ({m.slot_bytes} B each)")
        table = chunks.chunks(capacity, clen)
        self._chunk_why = (f"the {m.name} method's widest array is {m.slot_bytes} B/point; the device binds "
                           f"{limit} bytes per storage buffer and dispatches {groups}^2 workgroups")
        if len(table) > 1:
            log.info("wgpu tier: ring of %d slots split into %d chunks of up to %d slots (%s); every slot "
                     "is drawn", capacity, len(table), clen, self._chunk_why)
        return table

    def _setup_colour(self, channels: list[str]) -> None:
        cb = self.cfg.color_by
        self._cchan: Optional[str] = None
        if cb is None or cb == "none":
            self._cmode = ColourMode.FIXED
        elif cb == "rgb":
            self._cmode, self._cchan = ColourMode.RGB, "rgb"
        elif cb in ("z", "height"):
            self._cmode = ColourMode.Z
        elif cb == "ingest_time":
            self._cmode = ColourMode.TIME
        else:
            self._cmode, self._cchan = ColourMode.SCALAR, cb
        if self._cchan is not None and self._cchan not in channels:
            log.warning("wgpu tier: colour channel %r is not stored in the ring (channels %s); "
                        "drawing the single colour", self._cchan, channels)
            self._cmode, self._cchan = ColourMode.FIXED, None

    def _buf(self, size: int, usage: int, label: str) -> Any:
        return self.device.create_buffer(size=max(int(size), 16), usage=usage, label=label)

    def _create_resources(self) -> None:
        wgpu, dev = self._wgpu, self.device
        BU = wgpu.BufferUsage
        cap = self.render_capacity
        sto = BU.STORAGE | BU.COPY_DST
        colour_words = self._cmode in (ColourMode.RGB, ColourMode.SCALAR)
        self._sets = [[{"pos": self._buf(n * 12, sto, f"pos{s}.{c}"),
                        "tms": self._buf(n * 8 if self._need_t else 16, sto, f"tms{s}.{c}"),
                        "imp": self._buf(n * 4 if self._need_imp else 16, sto, f"imp{s}.{c}"),
                        "col": self._buf(n * 4 if colour_words else 16, sto, f"col{s}.{c}")}
                       for c, (_, n) in enumerate(self._chunk_table)] for s in range(DATA_SETS)]
        nseg = self._nseg
        self._state = self._buf(Gpu.STATE_STRIDE * nseg, BU.STORAGE | BU.INDIRECT | BU.COPY_DST | BU.COPY_SRC,
                                "state")
        # colour range (ord_f min, max) in words 0, 1; words 4, 5: the quads method's counts
        # over all segments (survivors, drawn under the budget)
        self._rng = self._buf(32, BU.STORAGE | BU.COPY_DST, "range")
        self._dargs = self._buf(16, BU.STORAGE | BU.INDIRECT | BU.COPY_DST, "dispatch-args")
        self._params = self._buf(Gpu.PARAMS_STRIDE * nseg, BU.UNIFORM | BU.COPY_DST, "params")
        self._lut = self._buf(1024, sto, "lut")
        self._blod = self._buf(-(-cap // batches.BATCH_SLOTS) * 4, sto, "batch-lod")  # footprint LOD masks
        self.queue.write_buffer(self._lut, 0, np.ascontiguousarray(colormap.lut(self.cfg.colormap)).view(np.uint32))
        one = np.zeros(Gpu.STATE_STRIDE // 4, np.uint32)
        one[:16] = [6, 0, 0, 0, 0, 1, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0]
        self._state_reset = np.tile(one, nseg)
        self._rng_reset = np.array([0xFFFFFFFF, 0, 0, 0, 0, 0, 0, 0], np.uint32)
        self._row_bytes = (self.width * 4 + 255) // 256 * 256
        self._readback = self._buf(self._row_bytes * self.height, BU.MAP_READ | BU.COPY_DST, "readback")
        self._fence = [self._buf(Gpu.STATE_STRIDE * nseg, BU.MAP_READ | BU.COPY_DST, f"fence{s}") for s in range(2)]
        qs = None
        if self._ts:
            qs = dev.create_query_set(type=wgpu.QueryType.timestamp, count=4)
            self._ts_resolve = self._buf(32, BU.QUERY_RESOLVE | BU.COPY_SRC, "ts-resolve")
            self._ts_read = [self._buf(32, BU.MAP_READ | BU.COPY_DST, f"ts-read{s}") for s in range(2)]
        self._qs = qs
        if self._compact_on:
            self._compact = CompactPositions(self.device, self._bounds, cap, self._chunk_table, DATA_SETS)
        self._method = self._make_method()

    def _make_method(self) -> RasterMethod:
        """The raster method for the current size (its pipelines and size-bound buffers)."""
        gpu = Gpu(wgpu=self._wgpu, device=self.device, cfg=self.cfg, width=self.width, height=self.height,
                  capacity=self.render_capacity, cmode=int(self._cmode), naive_float32=self.naive_float32,
                  key64=self._key64, max_groups=self._max_groups, row_bytes=self._row_bytes, sets=self._sets,
                  params=self._params, state=self._state, rng=self._rng, dargs=self._dargs, lut=self._lut,
                  timestamps=self._qs, chunks=list(self._chunk_table), max_segments=self._nseg, compact=self._compact,
                  blod=self._blod)
        return self._method_cls(gpu)

    def resize(self, width: int, height: int) -> bool:
        """A target per size (the raster method's image and key buffers, the readback), kept
        for switching back; the ring's buffers are shared, so another size uploads nothing.
        The first draw at a new size builds its pipelines (lavapipe: some 100 ms)."""
        size = (int(width), int(height))
        if size == (self.width, self.height):
            return True
        targets = self.__dict__.setdefault("_targets", {})
        old = (self.width, self.height)
        targets[old] = (self._method, self._readback, self._row_bytes)
        if size in targets:
            self._method, self._readback, self._row_bytes = targets[size]
            self.width, self.height = size
            return True
        if size[0] * size[1] * 8 > int(self._limits.get("max-storage-buffer-binding-size", 2 ** 27)):
            return False  # the compute method's key buffer would not fit one binding
        self.width, self.height = size
        self._row_bytes = (size[0] * 4 + 255) // 256 * 256
        try:
            BU = self._wgpu.BufferUsage
            self._readback = self._buf(self._row_bytes * size[1], BU.MAP_READ | BU.COPY_DST, "readback")
            self._method = self._make_method()
        except Exception as e:  # noqa: BLE001 - e.g. a key buffer over the device's limit
            log.warning("wgpu tier cannot draw at %dx%d (%s); views get %dx%d", *size, e, *old)
            self.width, self.height = old
            self._method, self._readback, self._row_bytes = targets[old]
            return False
        return True

    # ------------------------------------------------------------------ frame
    def _wait_set(self, s: int) -> None:
        """Wait for the frame that last used set ``s`` (two frames ago); collect its GPU times."""
        if self._done[s]:
            # mapping the fence waits for the frame that wrote it (wgpu-py's
            # on_submitted_work_done_async is broken in 0.32 and waits for *all* work anyway)
            self._collect(s)
        if self._ts and self._ts_used[s]:
            b = self._ts_read[s]
            b.map_sync(self._wgpu.MapMode.READ)
            t = np.frombuffer(b.read_mapped(), np.uint64).copy()
            b.unmap()
            self._ts_used[s] = False
            if t[1] >= t[0] and t[3] >= t[2]:
                self._gpu_ms = {"gpu_compute": float(t[1] - t[0]) * 1e-6, "gpu_draw": float(t[3] - t[2]) * 1e-6}

    def _collect(self, s: int) -> None:
        """Map set ``s``'s fence (waits for its frame) and fill that frame's FrameStats with the
        GPU counters: ``drawn`` and ``extra`` removed_nonfinite / culled / occupied."""
        f = self._fence[s]
        f.map_sync(self._wgpu.MapMode.READ)
        st = self._state_sum(np.frombuffer(f.read_mapped(), np.uint32))
        f.unmap()
        self._done[s] = False
        bad, cut = self._cut[s]  # culled batches and LOD-dropped slots: counted here, never read by the GPU
        fs = self._stats[s]
        if fs is not None:
            fs.drawn = int(st[1])
            fs.extra.update({"occupied": int(st[13]) + cut, "removed_nonfinite": int(st[12]) + bad,
                             "survivors_before_budget": int(st[8]), "counters": "exact (read after the GPU finished)"})
            self._stats[s] = None
        self.nonfinite_total += int(st[12]) + bad

    def _state_sum(self, words: np.ndarray) -> np.ndarray:
        """The 16 state words summed over the segments' windows (counters add up; the
        method's own per-segment words 0, 10, 11 mean nothing summed)."""
        return words.reshape(self._nseg, Gpu.STATE_STRIDE // 4)[:, :16].astype(np.int64).sum(axis=0)

    @staticmethod
    def check_frame(frame: FrameInput) -> None:
        """Reject a malformed FrameInput with a ValueError naming the field (not a RenderError:
        another tier would fail on the same input)."""
        cap = int(frame.capacity)
        if cap < 1:
            raise ValueError(f"FrameInput.capacity must be >= 1, got {cap}")
        p = frame.positions
        if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < cap:
            raise ValueError(f"FrameInput.positions: expected ({cap}, 3), got {p.shape}")
        for name in ("importance", "t_ingest_ms"):
            a = getattr(frame, name)
            if a.shape[0] < cap:
                raise ValueError(f"FrameInput.{name}: expected {cap} entries, got {a.shape[0]}")
        if not 0 <= int(frame.size) <= cap:
            raise ValueError(f"FrameInput.size must be in 0..capacity ({cap}), got {frame.size}")
        if not 0 <= int(frame.head) < cap:
            raise ValueError(f"FrameInput.head must be in 0..capacity-1 ({cap - 1}), got {frame.head}")

    def render(self, frame: FrameInput, camera: Camera) -> FrameStats:
        if self._closed:
            raise RenderError("wgpu tier is closed")
        self.check_frame(frame)
        try:
            return self._render(frame, camera)
        except Exception as e:
            # the one set of point buffers may hold part of this frame now: no pick or survivor
            # query may read it as the last frame's
            self._last = None
            if isinstance(e, RenderError):
                raise
            raise RenderError(f"wgpu tier frame failed: {type(e).__name__}: {e}") from e

    def _render(self, frame: FrameInput, camera: Camera) -> FrameStats:
        t0 = time.perf_counter()
        s = self._frame_no % 2  # the fence (two frames in flight)
        d = self._frame_no % DATA_SETS  # the point buffers
        full = self._mark_dirty(frame)
        if self._culling is not None:  # before anything reduces the batch bounds
            self._culling.note(frame, full)
        elif self._compact is not None or self.cfg.lod_fill > 0:
            self._bounds.note(frame, full)
        masks = None
        if self.cfg.lod_fill > 0:  # the footprint LOD's masks (batches.lod_masks), from the same bounds
            if self._lod_bounds is not self._bounds:
                self._lod_bounds.note(frame, full)
            masks = self._lod_bounds.lod_masks(frame, camera, self.cfg, self.width, self.height)
        uploaded = self._upload(frame, d)
        n_slots = min(self.render_capacity, int(frame.capacity))
        segs = chunks.segments(int(frame.head), int(frame.size), int(frame.capacity), n_slots, self._chunk_table)
        if len(self._chunk_table) == 1:
            # one thread per logical index (oldest first); slots beyond the tier's are skipped
            segs[0].size = min(int(frame.size), int(frame.capacity), self.render_capacity)
        n_threads = sum(g.size for g in segs)
        groups_total = 0
        for g in segs:
            g.groups, g.gx, g.gy, _ = self._method.plan(g.size, frame.budget)
            g.group_base = groups_total
            groups_total += g.groups
        budget_on = self._method.plan(n_threads, frame.budget)[3]  # (as without culling)
        P = frame_params.build(self.cfg, frame, camera, self.width, self.height, self._cmode, self._cchan,
                               self.naive_float32, n_slots, segs[0].gx, segs[0].groups, self._view_cache)
        if self._compact is not None:  # settled batches encoded; per batch the words read for this view
            uploaded += self._compact.settle_step(frame, d)
            self._compact.frame(d, P, self._compact_force)
        runs, bad, cut, crange = ([], 0, 0, None) if self._culling is None else \
            self._culling.cut(frame, P, segs, self._chunk_table, self._nseg, self.render_capacity)
        if runs:
            groups_total = 0
            for g in runs:
                g.groups, g.gx, g.gy, _ = self._method.plan(g.size, frame.budget)
                g.group_base = groups_total
                groups_total += g.groups
        lbad, lcut, lrange, counted = self._lod_frame(frame, P, masks)
        bad += lbad
        if lrange is not None:  # the CPU-counted batches' share
            crange = lrange if crange is None else (min(crange[0], lrange[0]), max(crange[1], lrange[1]))
        # only now wait for the frame two before (its fence ``s``; wgpu-py's map waits for all
        # work submitted): planning, culling and the upload above ran while the GPU drew
        t_w0 = time.perf_counter()
        self._wait_set(s)
        t_wait = time.perf_counter() - t_w0
        self._cut[s] = (bad, cut + lcut)  # what the passes do not read, counted here
        walk = runs or segs
        q = self.queue
        q.write_buffer(self._params, 0, self._segment_params(P, segs + runs, n_slots, groups_total, len(segs)))
        q.write_buffer(self._state, 0, self._state_reset)
        rng = self._rng_reset
        if crange is not None:  # the culled batches' share of the automatic colour range
            rng = rng.copy()
            rng[0], rng[1] = crange
        q.write_buffer(self._rng, 0, rng)
        t_up = time.perf_counter()
        plan = FramePlan(set=d, n_threads=n_threads, groups=groups_total, gx=walk[0].gx, gy=walk[0].gy,
                         budget_on=budget_on, budget_n=frame.budget,
                         head=int(frame.head) % max(int(frame.capacity), 1),
                         capacity=int(frame.capacity), params=P, segments=segs, runs=runs)
        enc = self.device.create_command_encoder()
        self._method.encode(enc, plan)
        if self._ts:
            enc.resolve_query_set(self._qs, 0, 4, self._ts_resolve, 0)
            enc.copy_buffer_to_buffer(self._ts_resolve, 0, self._ts_read[s], 0, 32)
            self._ts_used[s] = True
        # the fence doubles as the (lagged) counter readout: copied now, read once the GPU is done
        enc.copy_buffer_to_buffer(self._state, 0, self._fence[s], 0, Gpu.STATE_STRIDE * self._nseg)
        q.submit([enc.finish()])
        self._done[s] = True
        t_sub = time.perf_counter()
        self._last, self._last_fence = plan, s
        self._frame_no += 1
        timings = {"wait": t_wait * 1e3, "upload": (t_up - t0 - t_wait) * 1e3,
                   "encode_submit": (t_sub - t_up) * 1e3, "cpu_total": (t_sub - t0) * 1e3}
        timings.update(self._gpu_ms)
        stats = FrameStats(drawn=None, timings_ms=timings, uploaded_bytes=uploaded,
                           extra={"fence": s, "render_capacity": self.render_capacity, "raster": self.raster,
                                  "gpu_timings_lag_frames": 2 if self._ts else None, "culled_points": cut,
                                  "lod_cpu_counted_batches": counted,
                                  "runs": len(walk), **(copy.deepcopy(self._compact.stats) if self._compact else {})})
        self._stats[s] = stats  # drawn/removed_nonfinite filled in once the GPU is done
        self._last_stats = stats
        return stats

    def _lod_frame(self, frame: FrameInput, P: np.ndarray,
                   masks: Optional[np.ndarray]) -> tuple[int, int, Optional[tuple[int, int]], int]:
        """The footprint LOD's part of a frame (``masks`` from ``batches.lod_masks``; None: off).
        Writes the mask words the passes test, the batches the CPU counts flagged
        (:meth:`Culling.lod_counted`), or, when no batch is thinned, clears the LOD flag so
        the passes run without the test. Returns what the passes will not see: (non-finite
        count, occupied slots, colour range words or None, batches the CPU counts)."""
        if masks is None:
            return 0, 0, None, 0
        if not masks.any():
            P["flags"] = int(P["flags"]) & ~int(Flag.BATCH_LOD)
            return 0, 0, None, 0
        bad, dropped, rng = 0, 0, None
        if self._culling is not None:  # dropped slots of whole thinned batches are never read
            auto = bool(int(P["flags"]) & Flag.RANGE_AUTO)
            masks, bad, dropped, rng = self._culling.lod_counted(frame, masks, auto, self.render_capacity)
        n = min(masks.size, self._blod.size // 4)
        self.queue.write_buffer(self._blod, 0, np.ascontiguousarray(masks[:n], np.uint32))
        counted = int(np.count_nonzero(masks[:n] & np.uint32(CPU_COUNTED)))
        return bad, dropped, (rng if rng is not None and rng[0] <= rng[1] else None), counted

    def _segment_params(self, P: np.ndarray, segs: list[chunks.Segment], n_slots: int, groups_total: int,
                        n_segments: int) -> bytes:
        """Every segment's Params record at :attr:`Gpu.PARAMS_STRIDE` (one segment: ``P``);
        the first ``n_segments`` are the frame's segments, the rest their runs after culling."""
        out = np.zeros(len(segs) * Gpu.PARAMS_STRIDE, np.uint8)
        glob = self._method_cls.global_groups
        single = len(self._chunk_table) == 1
        for g in segs:
            R = P.copy()
            if not single:  # (one chunk: the frame's own ring, as build() wrote it)
                R["head"], R["size"], R["capacity"], R["n_slots"] = g.head, g.size, g.capacity, g.capacity
            elif g.index >= n_segments:  # a run of the one chunk (its slots may wrap the ring's end)
                R["head"], R["size"] = g.head, g.size
            R["groups_x"] = g.gx
            R["groups_total"] = groups_total if glob else g.groups
            R["group_base"] = g.group_base if glob else 0
            R["slot_base"], R["logical_base"] = g.slot_base, g.logical_base
            o = g.index * Gpu.PARAMS_STRIDE
            out[o:o + PARAMS_DTYPE.itemsize] = np.frombuffer(R.tobytes(), np.uint8)
        return out.tobytes()

    # ------------------------------------------------------------------ output
    def read_image(self) -> np.ndarray:
        """(h, w, 4) uint8 of the last frame (waits for the GPU)."""
        enc = self.device.create_command_encoder()
        self._method.copy_image(enc, self._readback)
        self.queue.submit([enc.finish()])
        self._readback.map_sync(self._wgpu.MapMode.READ)
        if self._last is not None and self._done[self._last_fence]:
            self._collect(self._last_fence)  # the GPU is done with the last frame: free counters
        try:
            raw = np.frombuffer(self._readback.read_mapped(), np.uint8)
            img = raw.reshape(self.height, self._row_bytes)[:, :self.width * 4].reshape(self.height, self.width, 4).copy()
        finally:
            self._readback.unmap()
        return img

    def finish(self) -> Optional[FrameStats]:
        """Wait until the GPU finished the last frame; returns its FrameStats with the exact
        counters filled in (for a true ``frame_done`` time; not needed on the frame path)."""
        if self._last is None:
            return None
        if self._done[self._last_fence]:
            self._collect(self._last_fence)
        return self._last_stats

    def debug_counts(self) -> dict[str, int]:
        """Tests only (syncs the GPU): survivors of the cull, after the budget, and the draw count
        (compute: ``instance_count`` is the raster pass's count of points written)."""
        raw = np.frombuffer(self.queue.read_buffer(self._state), np.uint32)
        st = self._state_sum(raw)
        return {"culled": int(st[8]), "thinned": int(st[9]), "instance_count": int(st[1]),
                "vertex_count": int(raw[0])}

    def debug_survivors(self) -> np.ndarray:
        """Tests only (syncs the GPU): sorted slots the last frame draws."""
        if self._last is None:
            return np.zeros(0, np.int64)
        return self._method.survivors(self._last)

    # ------------------------------------------------------------------ picking
    def pick(self, x: float, y: float, pixel_ratio: float = 1.0) -> Optional[int]:
        """Slot of the point under window pixel (x, y) (logical px; ``pixel_ratio`` scales to
        the target's physical px), or None. The method reads the front-most point of each
        texel of the (2r+1)^2 block, r = pick_radius * pixel_ratio, in the last frame."""
        if self._last is None or self._closed:
            return None
        try:
            px, py = float(x) * pixel_ratio, float(y) * pixel_ratio
            r = float(self.cfg.pick_radius) * pixel_ratio
            block = pick_block(px, py, r, self.width, self.height)
            if block is None:
                return None
            ids, attrs = self._method.pick_block(self._last, *block)
            return resolve_pick(ids, attrs, block[0], block[1], px, py, r, self.cfg.pick_strategy)
        except Exception as e:
            raise RenderError(f"wgpu pick failed: {type(e).__name__}: {e}") from e

    # ------------------------------------------------------------------ misc
    def info(self) -> dict[str, Any]:
        return {"tier": self.tier, "adapter": adapter_summary(self.adapter), "adapter_choice": self._adapter_why,
                "backend": self.adapter.info.get("backend_type", ""), "limits": dict(self._limits),
                "ring_capacity": self.capacity, "render_capacity": self.render_capacity,
                "caps": list(self._caps), "chunks": len(self._chunk_table),
                "chunk_slots": self._chunk_table[0][1], "timestamps": self._ts, "naive_float32": self.naive_float32,
                "size": [self.width, self.height], "raster": self.raster, "raster_choice": self._raster_why,
                "compute_keys": None, "compact_positions": self._compact is not None,
                "compact_choice": self._compact_why,
                "compact_settle_frames": self._compact.settle if self._compact else None,
                **(self._compact.stats if self._compact else {}), **self._method.info()}

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self.queue.on_submitted_work_done_sync()
        except Exception:
            pass
        if self._method is not None:
            self._method.close()
        if self._compact is not None:
            self._compact.close()
        bufs = [b for per_set in getattr(self, "_sets", []) for S in per_set for b in S.values()]
        bufs += [getattr(self, n, None) for n in ("_state", "_rng", "_dargs", "_params", "_lut", "_blod", "_readback",
                                                   "_ts_resolve")]
        bufs += list(getattr(self, "_ts_read", [])) + list(getattr(self, "_fence", []))
        for b in bufs:
            if b is not None:
                try:
                    b.destroy()
                except Exception:
                    pass
        try:
            self.device.destroy()
        except Exception:
            pass
