"""The wgpu render tier: incremental upload, compute cull + compaction, indirect draw, picking.

Frame path (no Python loop over points, no readback):

1. upload the dirty slot ranges into the GPU buffer set ``k % 2`` (the other set may still
   be read by the previous frame; each set catches up on the ranges it missed);
2. compute ``cull`` (one thread per logical index, workgroup 256): occupancy, finite,
   time window, 6 frustum planes, LOD stride, importance sampling -> a keep flag and a
   count per workgroup; ``scan`` (one workgroup) turns the counts into offsets; ``emit``
   writes survivors in logical order as (slot, RGBA8 colour) + clip position, so the
   projection and colour are computed once per point, not once per quad vertex, and
   equal-depth ties resolve to the lower logical index; ``finalize`` writes the count
   into the ``drawIndirect`` arguments (with a budget, ``thin``/``thin_scan``/``thin_emit``
   + ``finalize_budget`` thin the survivors to the budget the same way);
3. ``draw_indirect`` of instanced quads (6 vertices per point) into an RGBA8 target, with
   a vertex/fragment variant specialised for the shape, size space and colour source.

At most two frames are in flight: before reusing buffer set ``s`` we wait for the frame
that last read it, which also bounds latency when the GPU is slower than the cadence.
The wait maps a 64-byte fence into which that frame copied its counters, so the
``FrameStats`` of a frame gets ``drawn`` / ``removed_nonfinite`` two frames later (or at
``read_image()``, which waits for the GPU anyway) without ever stalling for them.
"""
from __future__ import annotations

import logging
import math
import time
from typing import Any, Optional

import numpy as np

from ...config import RenderConfig
from .. import colormap
from ..base import FrameInput, FrameStats, Renderer, RenderError
from ..camera import Camera
from . import shaders
from .compute_raster import KEY64_FEATURES, ComputeRaster, choose_raster
from .device import adapter_summary, request_device, select_adapter
from .reference import budget_seed, seed_hash

log = logging.getLogger("pointflow.render.wgpu")

# word offsets in the Params uniform (see shaders.PARAMS)
_P_VP, _P_MODEL, _P_PLANES, _P_COLOR = 0, 16, 32, 56
(_P_VW, _P_VH, _P_PSIZE, _P_SSCALE, _P_NOW_HI, _P_NOW_LO, _P_WINDOW, _P_IMP_LO, _P_IMP_SCALE,
 _P_RANGE_LO, _P_RANGE_SCALE, _P_RANGE_HI) = range(60, 72)
(_P_HEAD, _P_SIZE, _P_CAP, _P_LOD, _P_SEED, _P_FLAGS, _P_BUDGET, _P_CMODE, _P_BSEED, _P_GX,
 _P_NSLOTS, _P_GTOTAL) = range(72, 84)
_P_WORDS = 84

F_WINDOW, F_IMPORTANCE, F_IMP_DEGENERATE = 1, 2, 4
F_WORLD_SIZE, F_ROUND, F_RANGE_AUTO, F_RANGE_DEGENERATE, F_COLOUR_IN_VS = 16, 32, 64, 128, 256
C_FIXED, C_RGB, C_SCALAR, C_Z, C_TIME = range(5)
NO_BUDGET = 0xFFFFFFFF
_EMIT_K = 8  # logical indices per thread in the emit pass (shaders.EMIT_K)
_MAX_GROUPS = 65535

#: test-only switch: draw with an absolute float32 model matrix instead of the float64
#: origin-relative view-projection (shows the large-coordinate error it avoids).
NAIVE_FLOAT32 = False

Range = tuple[int, int]


def merge_ranges(ranges: list[Range], capacity: int) -> list[Range]:
    """Sorted, non-overlapping, clipped to [0, capacity); wrapping ranges are split."""
    out: list[Range] = []
    for a, b in ranges:
        a, b = int(a), int(b)
        if b < a:  # wraps around the end of the ring
            out.extend([(a, capacity), (0, b)])
        else:
            out.append((a, b))
    out = sorted((max(a, 0), min(b, capacity)) for a, b in out if min(b, capacity) > max(a, 0))
    merged: list[Range] = []
    for a, b in out:
        if merged and a <= merged[-1][1]:
            merged[-1] = (merged[-1][0], max(merged[-1][1], b))
        else:
            merged.append((a, b))
    return merged


def _mat_cols(m: np.ndarray) -> np.ndarray:
    """float64 row-major 4x4 -> float32 column-major (WGSL mat4x4 layout)."""
    return np.ascontiguousarray(np.asarray(m, np.float64).T, dtype=np.float32).ravel()


class WgpuRenderer(Renderer):
    """GPU tier on wgpu. ``info()`` reports the adapter, limits, caps and timestamp support."""

    tier = "wgpu"

    def __init__(self, cfg: RenderConfig, capacity: int, channels: list[str], *,
                 adapter: Any = None, naive_float32: Optional[bool] = None,
                 key64: Optional[bool] = None, max_groups: Optional[int] = None):
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
        # key64=False (tests) forces the two-pass 32-bit variant where 64-bit atomics exist
        want64 = KEY64_FEATURES if self.raster == "compute" and key64 is not False else ()
        try:
            self.device, dinfo = request_device(adapter, bool(cfg.gpu_timestamps), want64)
        except Exception as e:
            raise RenderError(f"wgpu device request failed on {adapter.summary}: {e}") from e
        self.adapter = adapter
        self._adapter_why = why
        self.queue = self.device.queue
        self._ts = dinfo["timestamps"]
        self._limits = dinfo["limits"]
        self._key64 = bool(dinfo["features"])
        self._max_groups = int(max_groups or self._limits.get("max-compute-workgroups-per-dimension", _MAX_GROUPS))
        self._compute: Optional[ComputeRaster] = None
        self._caps: list[str] = []
        self.render_capacity = self._cap_capacity(int(capacity))
        self._setup_colour(channels)
        self._need_t = cfg.time_window_ms > 0 or self._cmode == C_TIME or cfg.pick_strategy == "recent_first"
        self._need_imp = bool(cfg.importance_sampling) or cfg.pick_strategy == "highest_importance"
        try:
            self._create_resources()
        except Exception as e:
            raise RenderError(f"wgpu tier setup failed: {type(e).__name__}: {e}") from e
        self._pending: list[list[Range]] = [[(0, self.render_capacity)], [(0, self.render_capacity)]]
        self._done = [False, False]
        self._stats: list[Optional[FrameStats]] = [None, None]
        self.nonfinite_total = 0
        self._ts_used = [False, False]
        self._frame_no = 0
        self._last: Optional[dict[str, Any]] = None
        self._origin: Optional[np.ndarray] = None
        self._gpu_ms: dict[str, float] = {}
        self._warned: set[str] = set()
        self._closed = False
        log.info("wgpu tier on %s (%s); capacity %d%s; timestamps %s", adapter.summary, why,
                 self.render_capacity, f" (capped: {'; '.join(self._caps)})" if self._caps else "",
                 "on" if self._ts else "off")
        log.info("wgpu tier raster method: %s (%s)%s", self.raster, self._raster_why,
                 f"; keys: {self.key_variant}" if self._compute else "")

    # ------------------------------------------------------------------ setup
    def _cap_capacity(self, capacity: int) -> int:
        lim = self._limits
        cap = max(capacity, 1)
        per_binding = int(lim.get("max-storage-buffer-binding-size", 2 ** 27))
        per_buffer = int(lim.get("max-buffer-size", 2 ** 28))
        max_pos = min(per_binding, per_buffer) // 12  # positions are the widest array (3 f32)
        if cap > max_pos:
            self._caps.append(f"ring capacity {cap} > {max_pos} points: positions would need {cap * 12} bytes, "
                              f"device allows {min(per_binding, per_buffer)} per storage buffer")
            cap = max_pos
        per_group = 256 * 16 if self.raster == "compute" else 256
        max_dispatch = int(lim.get("max-compute-workgroups-per-dimension", _MAX_GROUPS)) ** 2 * per_group
        if cap > max_dispatch:
            self._caps.append(f"capped to {max_dispatch} points by the compute dispatch limit")
            cap = max_dispatch
        for c in self._caps:
            log.warning("wgpu tier: %s; rendering only the first %d slots", c, cap)
        return cap

    def _setup_colour(self, channels: list[str]) -> None:
        cb = self.cfg.color_by
        self._cchan: Optional[str] = None
        if cb is None or cb == "none":
            self._cmode = C_FIXED
        elif cb == "rgb":
            self._cmode, self._cchan = C_RGB, "rgb"
        elif cb in ("z", "height"):
            self._cmode = C_Z
        elif cb == "ingest_time":
            self._cmode = C_TIME
        else:
            self._cmode, self._cchan = C_SCALAR, cb
        if self._cchan is not None and self._cchan not in channels:
            log.warning("wgpu tier: colour channel %r is not stored in the ring (channels %s); "
                        "drawing the single colour", self._cchan, channels)
            self._cmode, self._cchan = C_FIXED, None

    def _buf(self, size: int, usage: int, label: str) -> Any:
        return self.device.create_buffer(size=max(int(size), 16), usage=usage, label=label)

    def _create_resources(self) -> None:
        wgpu, dev = self._wgpu, self.device
        BU = wgpu.BufferUsage
        cap = self.render_capacity
        sto = BU.STORAGE | BU.COPY_DST
        self._sets = []
        for s in range(2):
            self._sets.append({
                "pos": self._buf(cap * 12, sto, f"pos{s}"),
                "tms": self._buf(cap * 8 if self._need_t else 16, sto, f"tms{s}"),
                "imp": self._buf(cap * 4 if self._need_imp else 16, sto, f"imp{s}"),
                "col": self._buf(cap * 4 if self._cmode in (C_RGB, C_SCALAR) else 16, sto, f"col{s}"),
            })
        self._idx1 = self._clip1 = self._flags = self._wgc = None
        if self.raster == "quads":
            # compacted survivors: (slot, packed RGBA8 colour) pairs
            self._idx1 = self._buf(cap * 8, BU.STORAGE | BU.COPY_SRC, "idx1")
            self._clip1 = self._buf(cap * 16, BU.STORAGE, "clip1")  # survivors' clip positions
            groups = (cap + 255) // 256
            self._flags = self._buf(groups * 256 * 4, BU.STORAGE, "keep-flags")   # per logical index
            self._wgc = self._buf((groups + _EMIT_K) * 4, BU.STORAGE, "workgroup-counts")  # -> offsets (scan)
        self._idx2: Optional[Any] = None
        self._clip2: Optional[Any] = None
        self._state = self._buf(64, BU.STORAGE | BU.INDIRECT | BU.COPY_DST | BU.COPY_SRC, "state")
        self._rng = self._buf(8, BU.STORAGE | BU.COPY_DST, "range")
        self._dargs = self._buf(16, BU.STORAGE | BU.INDIRECT | BU.COPY_DST, "dispatch-args")
        self._params = self._buf(_P_WORDS * 4, BU.UNIFORM | BU.COPY_DST, "params")
        self._lut = self._buf(1024, sto, "lut")
        self.queue.write_buffer(self._lut, 0, np.ascontiguousarray(colormap.lut(self.cfg.colormap)).view(np.uint32))
        self._state_reset = np.array([6, 0, 0, 0, 0, 1, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0], np.uint32)
        self._rng_reset = np.array([0xFFFFFFFF, 0], np.uint32)

        self._round = self.cfg.point_shape == "round"
        self._world = self.cfg.point_size_space == "world"
        self._p_pick = None
        w, h = self.width, self.height
        self._color_tex = self._depth_tex = None
        self._row_bytes = (w * 4 + 255) // 256 * 256
        self._readback = self._buf(self._row_bytes * h, BU.MAP_READ | BU.COPY_DST, "readback")
        self._pick_tex: Optional[dict[str, Any]] = None
        self._fence = [self._buf(64, BU.MAP_READ | BU.COPY_DST, f"fence{s}") for s in range(2)]
        if self._ts:
            self._qs = dev.create_query_set(type=wgpu.QueryType.timestamp, count=4)
            self._ts_resolve = self._buf(32, BU.QUERY_RESOLVE | BU.COPY_SRC, "ts-resolve")
            self._ts_read = [self._buf(32, BU.MAP_READ | BU.COPY_DST, f"ts-read{s}") for s in range(2)]
        self._bg_cache: dict[Any, Any] = {}
        if self.raster == "compute":
            self._compute = ComputeRaster(self, self._key64, self._max_groups)
            return
        self._create_quads()

    def _create_quads(self) -> None:
        """Pipelines and targets of the quads method (cull + compaction + indirect draw)."""
        wgpu, dev = self._wgpu, self.device
        TU = wgpu.TextureUsage
        w, h = self.width, self.height
        SS = wgpu.ShaderStage
        ro = {"type": wgpu.BufferBindingType.read_only_storage}
        rw = {"type": wgpu.BufferBindingType.storage}
        uni = {"type": wgpu.BufferBindingType.uniform}

        def bgl(kinds, vis, vis_of=None):
            vis_of = vis_of or {}
            return dev.create_bind_group_layout(entries=[
                {"binding": i, "visibility": vis_of.get(i, vis), "buffer": k} for i, k in enumerate(kinds)])

        self._bgl_cull = bgl([uni, ro, ro, ro, ro, rw, rw, rw, rw, ro, rw, rw, rw], SS.COMPUTE)
        self._bgl_thin = bgl([uni, ro, rw, rw, ro, rw, rw, rw], SS.COMPUTE)
        # only the pick fragment shader reads storage (t_ingest, importance)
        self._bgl_draw = bgl([uni, ro, ro, ro, ro, ro, ro, ro, ro], SS.VERTEX,
                             {2: SS.VERTEX | SS.FRAGMENT, 3: SS.VERTEX | SS.FRAGMENT})
        cull_mod = dev.create_shader_module(code=shaders.cull_source(self.naive_float32), label="cull")
        thin_mod = dev.create_shader_module(code=shaders.THIN, label="thin")
        pl_cull = dev.create_pipeline_layout(bind_group_layouts=[self._bgl_cull])
        pl_thin = dev.create_pipeline_layout(bind_group_layouts=[self._bgl_thin])
        self._pl_draw = dev.create_pipeline_layout(bind_group_layouts=[self._bgl_draw])
        self._p_cull = dev.create_compute_pipeline(layout=pl_cull, compute={"module": cull_mod, "entry_point": "cull"})
        cpipe = lambda layout, mod, entry: dev.create_compute_pipeline(  # noqa: E731
            layout=layout, compute={"module": mod, "entry_point": entry})
        self._p_scan = cpipe(pl_cull, cull_mod, "scan")
        self._p_emit = cpipe(pl_cull, cull_mod, "emit")
        self._p_final = cpipe(pl_cull, cull_mod, "finalize")
        self._p_final_b = cpipe(pl_cull, cull_mod, "finalize_budget")
        self._p_thin = cpipe(pl_thin, thin_mod, "thin")
        self._p_thin_scan = cpipe(pl_thin, thin_mod, "thin_scan")
        self._p_thin_emit = cpipe(pl_thin, thin_mod, "thin_emit")
        self._p_draw_cache: dict[bool, Any] = {}
        self._draw_pipeline(False)
        self._color_tex = dev.create_texture(size=(w, h, 1), format=wgpu.TextureFormat.rgba8unorm,
                                             usage=TU.RENDER_ATTACHMENT | TU.COPY_SRC, label="colour")
        self._color_view = self._color_tex.create_view()
        self._depth_tex = dev.create_texture(size=(w, h, 1), format=wgpu.TextureFormat.depth32float,
                                             usage=TU.RENDER_ATTACHMENT, label="depth")
        self._depth_view = self._depth_tex.create_view()

    def _draw_pipeline(self, colour_in_vs: bool) -> Any:
        """The draw pipeline variant (colour from the cull, or computed per vertex)."""
        p = self._p_draw_cache.get(colour_in_vs)
        if p is None:
            wgpu = self._wgpu
            code = shaders.draw_source(self._round, world_size=self._world, colour_in_vs=colour_in_vs)
            mod = self.device.create_shader_module(code=code, label="draw")
            p = self.device.create_render_pipeline(
                layout=self._pl_draw,
                vertex={"module": mod, "entry_point": "vs", "buffers": []},
                primitive={"topology": wgpu.PrimitiveTopology.triangle_list, "cull_mode": wgpu.CullMode.none},
                depth_stencil={"format": wgpu.TextureFormat.depth32float, "depth_write_enabled": True,
                               "depth_compare": wgpu.CompareFunction.less},
                multisample={"count": 1},
                fragment={"module": mod, "entry_point": "fs", "targets": [{"format": wgpu.TextureFormat.rgba8unorm}]},
            )
            self._p_draw_cache[colour_in_vs] = p
        return p

    def _bind(self, layout, bufs: list[Any]) -> Any:
        return self.device.create_bind_group(layout=layout, entries=[
            {"binding": i, "resource": {"buffer": b, "offset": 0, "size": b.size}} for i, b in enumerate(bufs)])

    def _groups(self, s: int, budget: bool) -> dict[str, Any]:
        key = (s, budget)
        g = self._bg_cache.get(key)
        if g is None:
            S = self._sets[s]
            data = [S["pos"], S["tms"], S["imp"], S["col"]]
            g = {"cull": self._bind(self._bgl_cull, [self._params, *data, self._idx1, self._state, self._rng,
                                                     self._dargs, self._lut, self._clip1, self._flags, self._wgc])}
            drawn_idx, drawn_clip = self._idx1, self._clip1
            if budget:
                if self._idx2 is None:
                    self._idx2 = self._buf(self.render_capacity * 8, self._wgpu.BufferUsage.STORAGE | self._wgpu.BufferUsage.COPY_SRC, "idx2")
                    self._clip2 = self._buf(self.render_capacity * 16, self._wgpu.BufferUsage.STORAGE, "clip2")
                g["thin"] = self._bind(self._bgl_thin, [self._params, self._idx1, self._idx2, self._state,
                                                        self._clip1, self._clip2, self._flags, self._wgc])
                drawn_idx, drawn_clip = self._idx2, self._clip2
            g["draw"] = self._bind(self._bgl_draw, [self._params, *data, drawn_idx, self._lut, self._rng, drawn_clip])
            self._bg_cache[key] = g
        return g

    # ------------------------------------------------------------------ upload
    def _upload(self, frame: FrameInput, s: int) -> int:
        """Write the ranges set ``s`` has missed; returns bytes uploaded."""
        cap = min(self.render_capacity, frame.capacity)
        ranges = merge_ranges(self._pending[s], cap)
        self._pending[s] = []
        S, q, total = self._sets[s], self.queue, 0
        for a, b in ranges:
            pos = np.ascontiguousarray(frame.positions[a:b], dtype=np.float32)
            q.write_buffer(S["pos"], a * 12, pos)
            total += pos.nbytes
            if self._need_t:
                t64 = np.asarray(frame.t_ingest_ms[a:b], dtype=np.float64)
                tt = np.empty((b - a, 2), np.float32)
                tt[:, 0] = t64
                tt[:, 1] = t64 - tt[:, 0]
                q.write_buffer(S["tms"], a * 8, tt)
                total += tt.nbytes
            if self._need_imp:
                imp = np.ascontiguousarray(frame.importance[a:b], dtype=np.float32)
                q.write_buffer(S["imp"], a * 4, imp)
                total += imp.nbytes
            if self._cmode == C_RGB:
                rgb = np.asarray(frame.channels["rgb"][a:b], dtype=np.uint32)
                packed = rgb[:, 0] | (rgb[:, 1] << 8) | (rgb[:, 2] << 16) | np.uint32(0xFF000000)
                q.write_buffer(S["col"], a * 4, packed)
                total += packed.nbytes
            elif self._cmode == C_SCALAR:
                v = np.ascontiguousarray(frame.channels[self._cchan][a:b], dtype=np.float32)
                q.write_buffer(S["col"], a * 4, v)
                total += v.nbytes
        return total

    def _mark_dirty(self, frame: FrameInput) -> None:
        cap = min(self.render_capacity, frame.capacity)
        origin = np.asarray(frame.origin, np.float64)
        full = frame.dirty is None or self._origin is None or not np.array_equal(origin, self._origin) \
            or self._last is None or self._last["capacity"] != frame.capacity
        d = [(0, cap)] if full else list(frame.dirty or [])
        for s in range(2):
            self._pending[s].extend(d)
            if len(self._pending[s]) > 64:  # keep the list short
                self._pending[s] = merge_ranges(self._pending[s], cap)
        self._origin = origin.copy()

    # ------------------------------------------------------------------ frame
    def _colour_range(self, frame: FrameInput) -> tuple[int, float, float, float]:
        """(flags, lo, hi, scale) for LUT colouring."""
        if self._cmode not in (C_SCALAR, C_Z, C_TIME):
            return 0, 0.0, 0.0, 0.0
        cr = self.cfg.color_range
        if isinstance(cr, (list, tuple)):
            lo, hi = float(cr[0]), float(cr[1])
            if self._cmode == C_Z:  # fixed range is in world z; positions are origin-relative
                lo, hi = lo - float(frame.origin[2]), hi - float(frame.origin[2])
        elif self._cmode == C_SCALAR and self._cchan in frame.channel_ranges:
            lo, hi = (float(v) for v in frame.channel_ranges[self._cchan])
        else:
            return F_RANGE_AUTO, 0.0, 0.0, 0.0
        if not hi > lo:
            return F_RANGE_DEGENERATE, lo, hi, 0.0
        return 0, lo, hi, float(np.float32(1.0 / (hi - lo)))

    @staticmethod
    def _importance_range(frame: FrameInput) -> tuple[float, float]:
        """Finite min/max over the occupied slots (the cadence normally sends this range)."""
        cap, size = int(frame.capacity), min(int(frame.size), int(frame.capacity))
        imp = frame.importance[:cap] if size == cap else frame.importance[frame.occupied_slots()]
        imp = imp[np.isfinite(imp)]
        return (float(imp.min()), float(imp.max())) if imp.size else (0.0, 0.0)

    def _params_for(self, frame: FrameInput, camera: Camera, n_slots: int, gx: int, groups: int) -> np.ndarray:
        cfg, w, h = self.cfg, self.width, self.height
        P = np.zeros(_P_WORDS, np.float32)
        U = P.view(np.uint32)
        origin = np.asarray(frame.origin, np.float64)
        if self.naive_float32:
            vp = camera.view_proj(w, h, None).astype(np.float32).astype(np.float64)
            model = np.eye(4)
            model[:3, 3] = origin.astype(np.float32)
            P[_P_VP:_P_VP + 16] = _mat_cols(vp)
            P[_P_MODEL:_P_MODEL + 16] = _mat_cols(model)
        else:
            P[_P_VP:_P_VP + 16] = _mat_cols(camera.view_proj(w, h, origin))
            P[_P_MODEL:_P_MODEL + 16] = _mat_cols(np.eye(4))
        P[_P_PLANES:_P_PLANES + 24] = camera.frustum_planes(w, h, origin).astype(np.float32).ravel()
        c = list(cfg.color) + [1.0] * (4 - len(cfg.color))
        P[_P_COLOR:_P_COLOR + 4] = np.round(np.clip(np.asarray(c[:4], np.float64), 0, 1) * 255.0) / 255.0
        P[_P_VW], P[_P_VH], P[_P_PSIZE] = w, h, cfg.point_size
        P[_P_SSCALE] = camera.proj(w, h)[1, 1] * h / 2.0
        now = float(frame.now_ms)
        P[_P_NOW_HI] = now
        P[_P_NOW_LO] = now - float(np.float32(now))
        P[_P_WINDOW] = cfg.time_window_ms
        flags = 0
        if cfg.time_window_ms > 0:
            flags |= F_WINDOW
        if cfg.importance_sampling:
            flags |= F_IMPORTANCE
            r = frame.channel_ranges.get("importance") or self._importance_range(frame)
            if not float(r[1]) > float(r[0]):
                flags |= F_IMP_DEGENERATE
            else:
                P[_P_IMP_LO] = float(r[0])
                P[_P_IMP_SCALE] = np.float32(1.0 / (float(r[1]) - float(r[0])))
        if cfg.point_size_space == "world":
            flags |= F_WORLD_SIZE
        if cfg.point_shape == "round":
            flags |= F_ROUND
        rflags, lo, hi, scale = self._colour_range(frame)
        flags |= rflags
        if rflags & F_RANGE_AUTO:  # the range is reduced during the cull: colour in the draw
            flags |= F_COLOUR_IN_VS
        P[_P_RANGE_LO], P[_P_RANGE_HI], P[_P_RANGE_SCALE] = lo, hi, scale
        U[_P_HEAD] = int(frame.head) % max(frame.capacity, 1)
        U[_P_SIZE] = min(int(frame.size), int(frame.capacity))
        U[_P_CAP] = int(frame.capacity)
        U[_P_LOD] = max(int(cfg.lod_stride), 1)
        U[_P_SEED] = seed_hash(frame.frame_seed)
        U[_P_BSEED] = budget_seed(frame.frame_seed)
        U[_P_FLAGS] = flags
        U[_P_BUDGET] = NO_BUDGET if frame.budget is None else max(0, min(int(frame.budget), NO_BUDGET - 1))
        U[_P_CMODE] = self._cmode
        U[_P_GX] = gx
        U[_P_NSLOTS] = n_slots
        U[_P_GTOTAL] = groups
        return P

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
        st = np.frombuffer(f.read_mapped(), np.uint32).copy()
        f.unmap()
        self._done[s] = False
        fs = self._stats[s]
        if fs is not None:
            fs.drawn = int(st[1])
            fs.extra.update({"occupied": int(st[13]), "removed_nonfinite": int(st[12]),
                             "survivors_before_budget": int(st[8]), "counters": "exact (read after the GPU finished)"})
            self._stats[s] = None
        self.nonfinite_total += int(st[12])

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
        except RenderError:
            raise
        except Exception as e:
            raise RenderError(f"wgpu tier frame failed: {type(e).__name__}: {e}") from e

    def _render(self, frame: FrameInput, camera: Camera) -> FrameStats:
        t0 = time.perf_counter()
        s = self._frame_no % 2
        self._wait_set(s)
        t_wait = time.perf_counter()
        self._mark_dirty(frame)
        uploaded = self._upload(frame, s)
        n_slots = min(self.render_capacity, int(frame.capacity))
        # one thread per logical index (oldest first); a capped ring renders its oldest slots
        n_threads = min(int(frame.size), int(frame.capacity), self.render_capacity)
        if self._compute is not None:
            groups = self._compute.groups_for(n_threads)
            gx, gy = self._compute.grid(groups)
            # a budget at or above the occupied slots can never bite: no budget passes
            budget = frame.budget is not None and int(frame.budget) < n_threads
        else:
            groups = max(1, math.ceil(n_threads / 256))
            gx = min(groups, self._max_groups)
            gy = math.ceil(groups / gx)
            budget = frame.budget is not None
        P = self._params_for(frame, camera, n_slots, gx, groups)
        q = self.queue
        q.write_buffer(self._params, 0, P)
        q.write_buffer(self._state, 0, self._state_reset)
        q.write_buffer(self._rng, 0, self._rng_reset)
        t_up = time.perf_counter()

        enc = self.device.create_command_encoder()
        if self._compute is not None:
            fl = int(P.view(np.uint32)[_P_FLAGS])
            self._compute.set_variant(bool(fl & F_WINDOW), int(P.view(np.uint32)[_P_LOD]) > 1,
                                      bool(fl & F_IMPORTANCE), bool(fl & F_RANGE_AUTO))
            self._compute.encode(enc, s, groups, budget, {"qs": self._qs} if self._ts else None,
                                 bool(int(P.view(np.uint32)[_P_FLAGS]) & F_RANGE_AUTO))
        else:
            self._encode_quads(enc, s, budget, gx, gy, groups, P)
        if self._ts:
            enc.resolve_query_set(self._qs, 0, 4, self._ts_resolve, 0)
            enc.copy_buffer_to_buffer(self._ts_resolve, 0, self._ts_read[s], 0, 32)
            self._ts_used[s] = True
        # the fence doubles as the (lagged) counter readout: copied now, read once the GPU is done
        enc.copy_buffer_to_buffer(self._state, 0, self._fence[s], 0, 64)
        q.submit([enc.finish()])
        self._done[s] = True
        t_sub = time.perf_counter()
        self._last = {"set": s, "budget": budget, "capacity": int(frame.capacity), "groups": groups,
                      "size": n_threads, "budget_n": frame.budget,
                      "head": int(frame.head) % max(int(frame.capacity), 1)}
        self._frame_no += 1
        timings = {"wait": (t_wait - t0) * 1e3, "upload": (t_up - t_wait) * 1e3,
                   "encode_submit": (t_sub - t_up) * 1e3, "cpu_total": (t_sub - t0) * 1e3}
        timings.update(self._gpu_ms)
        stats = FrameStats(drawn=None, timings_ms=timings, uploaded_bytes=uploaded,
                           extra={"buffer_set": s, "render_capacity": self.render_capacity, "raster": self.raster,
                                  "gpu_timings_lag_frames": 2 if self._ts else None})
        self._stats[s] = stats  # drawn/removed_nonfinite filled in once the GPU is done
        self._last["stats"] = stats
        return stats

    def _encode_quads(self, enc: Any, s: int, budget: bool, gx: int, gy: int, groups: int, P: np.ndarray) -> None:
        """Record the quads method: cull + compaction (+ budget thinning), indirect draw."""
        wgpu = self._wgpu
        g = self._groups(s, budget)
        cpass_kw, rpass_kw = {}, {}
        if self._ts:
            cpass_kw["timestamp_writes"] = {"query_set": self._qs, "beginning_of_pass_write_index": 0,
                                            "end_of_pass_write_index": 1}
            rpass_kw["timestamp_writes"] = {"query_set": self._qs, "beginning_of_pass_write_index": 2,
                                            "end_of_pass_write_index": 3}
        cp = enc.begin_compute_pass(**cpass_kw)
        cp.set_bind_group(0, g["cull"])
        cp.set_pipeline(self._p_cull)
        cp.dispatch_workgroups(gx, gy, 1)
        cp.set_pipeline(self._p_scan)
        cp.dispatch_workgroups(1, 1, 1)
        cp.set_pipeline(self._p_emit)
        cp.dispatch_workgroups(math.ceil(groups / _EMIT_K), 1, 1)
        cp.set_pipeline(self._p_final)
        cp.dispatch_workgroups(1, 1, 1)
        if budget:
            cp.set_bind_group(0, g["thin"])
            cp.set_pipeline(self._p_thin)
            cp.dispatch_workgroups_indirect(self._dargs, 0)
            cp.set_pipeline(self._p_thin_scan)
            cp.dispatch_workgroups(1, 1, 1)
            cp.set_pipeline(self._p_thin_emit)
            cp.dispatch_workgroups_indirect(self._dargs, 0)
            cp.set_pipeline(self._p_final_b)
            cp.set_bind_group(0, g["cull"])
            cp.dispatch_workgroups(1, 1, 1)
        cp.end()
        bg = self.cfg.background
        rp = enc.begin_render_pass(
            color_attachments=[{"view": self._color_view, "load_op": wgpu.LoadOp.clear,
                                "store_op": wgpu.StoreOp.store,
                                "clear_value": (float(bg[0]), float(bg[1]), float(bg[2]), 1.0)}],
            depth_stencil_attachment={"view": self._depth_view, "depth_clear_value": 1.0,
                                      "depth_load_op": wgpu.LoadOp.clear, "depth_store_op": wgpu.StoreOp.store},
            **rpass_kw)
        rp.set_pipeline(self._draw_pipeline(bool(int(P.view(np.uint32)[_P_FLAGS]) & F_COLOUR_IN_VS)))
        rp.set_bind_group(0, g["draw"])
        rp.draw_indirect(self._state, 0)
        rp.end()

    # ------------------------------------------------------------------ output
    def read_image(self) -> np.ndarray:
        """(h, w, 4) uint8 of the last frame (waits for the GPU)."""
        wgpu = self._wgpu
        enc = self.device.create_command_encoder()
        if self._compute is not None:  # the resolve pass wrote the image with the readback's pitch
            enc.copy_buffer_to_buffer(self._compute.img, 0, self._readback, 0, self._readback.size)
        else:
            enc.copy_texture_to_buffer({"texture": self._color_tex, "mip_level": 0, "origin": (0, 0, 0)},
                                       {"buffer": self._readback, "offset": 0, "bytes_per_row": self._row_bytes,
                                        "rows_per_image": self.height},
                                       (self.width, self.height, 1))
        self.queue.submit([enc.finish()])
        self._readback.map_sync(wgpu.MapMode.READ)
        if self._last is not None and self._done[self._last["set"]]:
            self._collect(self._last["set"])  # the GPU is done with the last frame: free counters
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
        s = self._last["set"]
        if self._done[s]:
            self._collect(s)
        return self._last.get("stats")

    def debug_counts(self) -> dict[str, int]:
        """Tests only (syncs the GPU): survivors of the cull, after the budget, and the draw count
        (compute: ``instance_count`` is the raster pass's count of points written)."""
        st = np.frombuffer(self.queue.read_buffer(self._state), np.uint32)
        return {"culled": int(st[8]), "thinned": int(st[9]), "instance_count": int(st[1]),
                "vertex_count": int(st[0])}

    def debug_survivors(self) -> np.ndarray:
        """Tests only (syncs the GPU): sorted slots the last frame draws."""
        if self._compute is not None:
            L = self._last
            if L is None:
                return np.zeros(0, np.int64)
            logical = self._compute.debug_keep(L["set"], L["groups"], L["size"], L["budget"])
            if L["budget"]:
                logical = logical[:max(int(L["budget_n"]), 0)]
            return np.sort((L["head"] + logical.astype(np.int64)) % max(L["capacity"], 1))
        c = self.debug_counts()
        buf = self._idx2 if self._last and self._last["budget"] else self._idx1
        n = c["instance_count"]
        if n == 0:
            return np.zeros(0, np.int64)
        idx = np.frombuffer(self.queue.read_buffer(buf, 0, n * 8), np.uint32)[0::2]
        return np.sort(idx.astype(np.int64))

    # ------------------------------------------------------------------ picking
    def _ensure_pick(self) -> None:
        if self._pick_tex is not None:
            return
        wgpu, dev = self._wgpu, self.device
        TU, TF = wgpu.TextureUsage, wgpu.TextureFormat
        w, h = self.width, self.height
        pick_mod = dev.create_shader_module(code=shaders.draw_source(self._round, pick=True, world_size=self._world),
                                            label="pick")
        self._p_pick = dev.create_render_pipeline(
            layout=self._pl_draw,
            vertex={"module": pick_mod, "entry_point": "vs", "buffers": []},
            primitive={"topology": wgpu.PrimitiveTopology.triangle_list, "cull_mode": wgpu.CullMode.none},
            depth_stencil={"format": TF.depth32float, "depth_write_enabled": True,
                           "depth_compare": wgpu.CompareFunction.less},
            multisample={"count": 1},
            fragment={"module": pick_mod, "entry_point": "fs_pick",
                      "targets": [{"format": TF.r32uint}, {"format": TF.rgba32float}]},
        )
        ids = dev.create_texture(size=(w, h, 1), format=TF.r32uint, usage=TU.RENDER_ATTACHMENT | TU.COPY_SRC)
        attrs = dev.create_texture(size=(w, h, 1), format=TF.rgba32float, usage=TU.RENDER_ATTACHMENT | TU.COPY_SRC)
        depth = dev.create_texture(size=(w, h, 1), format=TF.depth32float, usage=TU.RENDER_ATTACHMENT)
        self._pick_tex = {"ids": ids, "attrs": attrs, "depth": depth, "ids_view": ids.create_view(),
                          "attrs_view": attrs.create_view(), "depth_view": depth.create_view()}

    def pick(self, x: float, y: float, pixel_ratio: float = 1.0) -> Optional[int]:
        """Slot of the point under window pixel (x, y) (logical px; ``pixel_ratio`` scales to
        the target's physical px), or None. Runs a pick pass over the last frame's compacted
        points restricted by a scissor to the (2r+1)^2 block, r = pick_radius * pixel_ratio."""
        if self._last is None or self._closed:
            return None
        try:
            return self._pick(float(x), float(y), float(pixel_ratio))
        except Exception as e:
            raise RenderError(f"wgpu pick failed: {type(e).__name__}: {e}") from e

    def _pick(self, x: float, y: float, pixel_ratio: float) -> Optional[int]:
        wgpu = self._wgpu
        px, py = x * pixel_ratio, y * pixel_ratio
        r = float(self.cfg.pick_radius) * pixel_ratio
        ri = int(math.ceil(r))
        x0, x1 = max(int(math.floor(px)) - ri, 0), min(int(math.floor(px)) + ri + 1, self.width)
        y0, y1 = max(int(math.floor(py)) - ri, 0), min(int(math.floor(py)) + ri + 1, self.height)
        if x1 <= x0 or y1 <= y0:
            return None
        bw, bh = x1 - x0, y1 - y0
        if self._compute is not None:
            ids, attrs = self._compute.pick_block(self._last["set"], x0, y0, bw, bh)
            return resolve_pick(ids, attrs, x0, y0, px, py, r, self.cfg.pick_strategy)
        self._ensure_pick()
        T = self._pick_tex
        g = self._groups(self._last["set"], self._last["budget"])
        enc = self.device.create_command_encoder()
        rp = enc.begin_render_pass(
            color_attachments=[
                {"view": T["ids_view"], "load_op": wgpu.LoadOp.clear, "store_op": wgpu.StoreOp.store,
                 "clear_value": (0, 0, 0, 0)},
                {"view": T["attrs_view"], "load_op": wgpu.LoadOp.clear, "store_op": wgpu.StoreOp.store,
                 "clear_value": (1.0, 0.0, 0.0, 0.0)}],
            depth_stencil_attachment={"view": T["depth_view"], "depth_clear_value": 1.0,
                                      "depth_load_op": wgpu.LoadOp.clear, "depth_store_op": wgpu.StoreOp.store})
        rp.set_scissor_rect(x0, y0, bw, bh)
        rp.set_pipeline(self._p_pick)
        rp.set_bind_group(0, g["draw"])
        rp.draw_indirect(self._state, 0)
        rp.end()
        row_ids = (bw * 4 + 255) // 256 * 256
        row_attr = (bw * 16 + 255) // 256 * 256
        BU = wgpu.BufferUsage
        b_ids = self._buf(row_ids * bh, BU.MAP_READ | BU.COPY_DST, "pick-ids")
        b_attr = self._buf(row_attr * bh, BU.MAP_READ | BU.COPY_DST, "pick-attrs")
        for tex, buf, row in ((T["ids"], b_ids, row_ids), (T["attrs"], b_attr, row_attr)):
            enc.copy_texture_to_buffer({"texture": tex, "mip_level": 0, "origin": (x0, y0, 0)},
                                       {"buffer": buf, "offset": 0, "bytes_per_row": row, "rows_per_image": bh},
                                       (bw, bh, 1))
        self.queue.submit([enc.finish()])
        b_ids.map_sync(wgpu.MapMode.READ)
        ids = np.frombuffer(b_ids.read_mapped(), np.uint32).reshape(bh, row_ids // 4)[:, :bw].copy()
        b_ids.unmap()
        b_attr.map_sync(wgpu.MapMode.READ)
        attrs = np.frombuffer(b_attr.read_mapped(), np.float32).reshape(bh, row_attr // 4)[:, :bw * 4]
        attrs = attrs.reshape(bh, bw, 4).copy()
        b_attr.unmap()
        b_ids.destroy()
        b_attr.destroy()
        return resolve_pick(ids, attrs, x0, y0, px, py, r, self.cfg.pick_strategy)

    # ------------------------------------------------------------------ misc
    def info(self) -> dict[str, Any]:
        return {"tier": self.tier, "adapter": adapter_summary(self.adapter), "adapter_choice": self._adapter_why,
                "backend": self.adapter.info.get("backend_type", ""), "limits": dict(self._limits),
                "ring_capacity": self.capacity, "render_capacity": self.render_capacity,
                "caps": list(self._caps), "timestamps": self._ts, "naive_float32": self.naive_float32,
                "size": [self.width, self.height], "raster": self.raster, "raster_choice": self._raster_why,
                "compute_keys": self.key_variant if self._compute else None}

    @property
    def key_variant(self) -> str:
        """The compute method's depth-key variant (deterministic either way)."""
        return "64-bit atomicMax" if self._key64 else "2x32-bit (depth pass, then index pass)"

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self.queue.on_submitted_work_done_sync()
        except Exception:
            pass
        bufs = [b for S in getattr(self, "_sets", []) for b in S.values()]
        bufs += [getattr(self, n, None) for n in ("_idx1", "_idx2", "_clip1", "_clip2", "_flags", "_wgc", "_state", "_rng", "_dargs", "_params",
                                                   "_lut", "_readback", "_ts_resolve")]
        bufs += list(getattr(self, "_ts_read", [])) + list(getattr(self, "_fence", []))
        for b in bufs:
            if b is not None:
                try:
                    b.destroy()
                except Exception:
                    pass
        texs = [getattr(self, "_color_tex", None), getattr(self, "_depth_tex", None)]
        if self._pick_tex:
            texs += [self._pick_tex["ids"], self._pick_tex["attrs"], self._pick_tex["depth"]]
        for t in texs:
            if t is not None:
                try:
                    t.destroy()
                except Exception:
                    pass
        self._bg_cache.clear()
        if self._compute is not None:
            self._compute.close()
        self._pick_tex = None
        try:
            self.device.destroy()
        except Exception:
            pass


def resolve_pick(ids: np.ndarray, attrs: np.ndarray, x0: int, y0: int, px: float, py: float,
                 radius: float, strategy: str) -> Optional[int]:
    """Choose one slot from a block of pick texels (ids = slot+1, attrs = depth, importance,
    t_hi, t_lo). Only texels whose centre is within ``radius`` of (px, py) count.

    Orders (first key wins, later keys break ties): nearest = (screen distance, depth, slot);
    highest_importance = (-importance, distance, depth, slot); recent_first = (-t_ingest,
    distance, depth, slot). Each texel holds the front-most point there, so a point hidden
    behind another is never picked.
    """
    bh, bw = ids.shape
    yy, xx = np.mgrid[0:bh, 0:bw]
    d2 = (xx + x0 + 0.5 - px) ** 2 + (yy + y0 + 0.5 - py) ** 2
    if radius < 0.5:  # radius 0: only the texel under the cursor
        m = (ids > 0) & (xx + x0 == int(np.floor(px))) & (yy + y0 == int(np.floor(py)))
    else:
        m = (ids > 0) & (d2 <= radius * radius + 1e-9)
    if not m.any():
        return None
    slot = ids[m].astype(np.int64) - 1
    depth = attrs[..., 0][m].astype(np.float64)
    dist = d2[m]
    if strategy == "highest_importance":
        keys = (slot, depth, dist, -attrs[..., 1][m].astype(np.float64))
    elif strategy == "recent_first":
        t = attrs[..., 2][m].astype(np.float64) + attrs[..., 3][m].astype(np.float64)
        keys = (slot, depth, dist, -t)
    else:
        keys = (slot, depth, dist)
    order = np.lexsort(keys)  # last key is primary
    return int(slot[order[0]])
