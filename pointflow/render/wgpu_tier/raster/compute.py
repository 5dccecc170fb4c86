"""The compute raster method of the wgpu tier (``render.raster: compute``).

Instead of compaction + an indirect instanced-quad draw, each frame is:

1. ``clear_buffer`` of the per-pixel key buffer (``W*H`` keys);
2. one pass over the occupied slots (workgroups of 256 threads, K = 16 points each, a
   workgroup covering 4096 consecutive logical indices; a 2-D grid beyond 65,535
   workgroups): every per-point test (occupancy, finite, time window, frustum incl. near,
   LOD stride, importance sampling, budget) fused with the projection and an atomic write
   of the point's depth key into every pixel of its footprint (the rules of
   ``render/base.py``: square / round footprints of s px, world-size per point);
3. one pass per pixel resolving the winning key to its colour (single colour, rgb, scalar
   colormaps, z, ingest time; the auto range is reduced in pass 2) or the background, into
   an RGBA8 image buffer with the readback's row pitch.

Key encoding (the buffer is cleared to 0 and written with atomicMax, so keys are stored
inverted: the largest stored value is the smallest key): ``key = (bits(w) << 32) | logical``
with ``w`` the clip w of the point, i.e. its linear view depth in world units (``w = -z_view
> 0`` after the near test), a float32 whose bit pattern orders like the number for positive
values. The relative precision is 2^-24 whatever near/far are (0.03 mm at 500 m), unlike
the hyperbolic ``z/w`` of a depth buffer; a smaller w always gives a smaller key, so
quantisation can never let a farther point win, and equal depths fall back to the lower
logical index. With ``shader-int64-atomic-min-max`` the whole key is one 64-bit atomicMax
(``wgsl/raster_key64.wgsl``); otherwise two passes of 32-bit atomics: ``atomicMax(~bits(w))``
per pixel, then the same pass again writes ``atomicMax(~logical)`` where its depth equals the
pixel's winner (``wgsl/raster_key32.wgsl``).

With a budget below the survivors two more passes count the survivors and the thinned
survivors per workgroup (a prefix sum gives each workgroup its first rank, so the hard cap
keeps the first b in logical order, as the cpu tier does).

Picking reads the key buffer of the last frame: a gather pass over the (2r+1)^2 block
under the cursor writes the winners' slots and attributes; no re-render.
"""
from __future__ import annotations

import math
from typing import Any, Optional

import numpy as np

from ...batches import BATCH_SHIFT
from .. import edl
from ..layout import CPARAMS_DTYPE, Flag
from .base import FramePlan, Gpu, RasterMethod, destroy_all

#: adapter features for the single-atomic 64-bit key
KEY64_FEATURES = ("shader-int64", "shader-int64-atomic-min-max")
#: points per thread (a workgroup of 256 covers 256 * K consecutive logical indices; row j
#: of a workgroup is 256 consecutive indices, so rows in order are logical order)
K = 16
# raster.wgsl splits a workgroup's range in three pieces at most for the footprint LOD's walk:
# it spans two batches at most (and the segment's wrap)
assert 256 * K <= 1 << BATCH_SHIFT
_MODES = {"count": 0, "thin": 1, "scan": 1, "raster": 2, "index": 2, "debug": 3}


class ComputeRaster(RasterMethod):
    name = "compute"
    points_per_group = 256 * K
    slot_bytes = 12        # positions
    global_groups = True   # budget offsets over the whole ring

    @classmethod
    def wanted_features(cls, cfg, key64: Optional[bool]) -> tuple[str, ...]:
        # key64=False (tests) forces the two-pass 32-bit variant where 64-bit atomics exist
        return KEY64_FEATURES if key64 is not False else ()

    def __init__(self, gpu: Gpu):
        super().__init__(gpu)
        g = gpu
        BU, SS = g.wgpu.BufferUsage, g.wgpu.ShaderStage
        self.key64 = bool(g.key64)
        self.n_px = g.width * g.height
        self.keys = g.buffer(self.n_px * (8 if self.key64 else 4), BU.STORAGE | BU.COPY_DST, "keys")
        self.ikeys = g.buffer(16 if self.key64 else self.n_px * 4, BU.STORAGE | BU.COPY_DST, "index-keys")
        self.wgc = g.buffer((self.groups_for(g.capacity) + g.max_segments + 1) * 4, BU.STORAGE, "workgroup-counts")
        self.dbg = g.buffer(16, BU.STORAGE, "debug-flags")
        self.cparams = g.buffer(CPARAMS_DTYPE.itemsize, BU.UNIFORM | BU.COPY_DST, "compute-params")
        self._cparams_key: Optional[tuple] = None  # what the buffer holds (write_cparams)
        self.img = g.buffer(g.row_bytes * g.height, BU.STORAGE | BU.COPY_SRC, "image")  # readback pitch
        self.pick_buf: Optional[Any] = None
        head = ["uniform", "uniform", "read", "read", "read", "read"]
        # bindings 12, 13: the compact positions' words and batch table (dummies when off)
        self.bgl_raster = g.layout(head + ["rw"] * 6 + ["read"] * 3, SS.COMPUTE)
        self.dummy = g.buffer(32, BU.STORAGE, "no-compact")
        self.bgl_resolve = g.layout(head + ["read"] * 4 + ["rw", "uniform"], SS.COMPUTE)
        # eye-dome lighting in the resolve pass, from the key buffer's depths (EDL constant)
        self.edl_on = bool(g.cfg.edl.enabled)
        E = edl.params(g.cfg.edl, g.width, g.height, g.row_bytes // 4)
        self.edl = g.buffer(E.nbytes, BU.UNIFORM | BU.COPY_DST, "edl-params")
        g.queue.write_buffer(self.edl, 0, E.tobytes())
        kf = "key64" if self.key64 else "key32"
        self.raster_files = ("common.wgsl", "scan.wgsl", f"raster_{kf}.wgsl", "raster.wgsl")
        self.resolve_files = ("common.wgsl", "lut_colour.wgsl", f"resolve_{kf}.wgsl", "resolve_head.wgsl")
        # constants of every variant: shape and size space (the splat loop carries no branch on them)
        self.fixed = {"ROUND": g.cfg.point_shape == "round", "WORLD": g.cfg.point_size_space == "world",
                      "NAIVE": g.naive_float32, "K": K,
                      "COMPACT": g.compact is not None,
                      "BATCH": g.compact.batch if g.compact is not None else 16384}
        self.pipes: dict[Any, Any] = {}
        self.bg_cache: dict[tuple[int, int, int], dict[str, Any]] = {}

    # ------------------------------------------------------------------ helpers
    def groups_for(self, n: int) -> int:
        return max(1, math.ceil(int(n) / (256 * K)))

    def plan(self, n_threads: int, budget: Optional[int]) -> tuple[int, int, int, bool]:
        groups = self.groups_for(n_threads)
        gx = min(groups, self.gpu.max_groups)
        # a budget at or above the occupied slots can never bite: no budget passes
        return groups, gx, math.ceil(groups / gx), budget is not None and int(budget) < n_threads

    @staticmethod
    def variant(plan: FramePlan, cmode: int) -> dict[str, Any]:
        """Which per-point tests and colour this frame's pipelines carry (override constants)."""
        fl = int(plan.params["flags"])
        return {"HAS_WINDOW": bool(fl & Flag.WINDOW), "HAS_LOD": int(plan.params["lod_stride"]) > 1,
                "HAS_BLOD": bool(fl & Flag.BATCH_LOD),
                "HAS_IMP": bool(fl & Flag.IMPORTANCE), "RANGE_AUTO": bool(fl & Flag.RANGE_AUTO), "CMODE": int(cmode)}

    def _raster_pipe(self, name: str, var: dict[str, Any]) -> Any:
        key = (name, tuple(sorted(var.items())))
        p = self.pipes.get(key)
        if p is None:
            consts = {**self.fixed, **var, "MODE": _MODES[name]}
            if not self.key64:
                consts["INDEX_PASS"] = name == "index"
            p = self.gpu.compute_pipeline(self.bgl_raster, self.raster_files, "scan" if name == "scan" else "main",
                                          name, **consts)
            self.pipes[key] = p
        return p

    def _resolve_pipe(self, cmode: int, range_auto: bool) -> Any:
        key = ("resolve", cmode, range_auto)
        p = self.pipes.get(key)
        if p is None:
            p = self.gpu.compute_pipeline(self.bgl_resolve, self.resolve_files + ("edl.wgsl", "resolve.wgsl"), "main",
                                          "resolve", CMODE=cmode, RANGE_AUTO=range_auto, EDL=self.edl_on)
            self.pipes[key] = p
        return p

    def _head(self, s: int, seg: Any) -> list[Any]:
        g = self.gpu
        return [g.params_at(seg.index), self.cparams, *g.data(s, seg.chunk), self.keys, self.ikeys]

    def groups(self, s: int, seg: Any) -> dict[str, Any]:
        """Bind groups of buffer set ``s`` for segment ``seg`` (its Params, its chunk's data;
        the counters are one set for the whole ring)."""
        key = (s, seg.index, seg.chunk)
        bg = self.bg_cache.get(key)
        if bg is None:
            g = self.gpu
            bg = {"raster": g.bind(self.bgl_raster, self._head(s, seg) + [g.state_at(0), g.rng, self.wgc, self.dbg]
                                   + self._compact_bufs(s, seg)),
                  "resolve": g.bind(self.bgl_resolve, self._head(s, seg) + [g.lut, g.rng, self.img, self.edl])}
            self.bg_cache[key] = bg
        return bg

    def _compact_bufs(self, s: int, seg: Any) -> list[Any]:
        c = self.gpu.compact
        bufs = [self.dummy, self.dummy] if c is None else [c.qpos[s][seg.chunk], c.table[s]]
        return bufs + [self.gpu.blod]

    def write_cparams(self, gx: int, budget_on: bool, pick: tuple[int, int, int, int] = (0, 0, 0, 0)) -> None:
        key = (gx, bool(budget_on), tuple(pick), tuple(self.gpu.cfg.background))
        if key == self._cparams_key:  # the buffer holds them already (queue writes are ordered)
            return
        self._cparams_key = key
        b = self.gpu.cfg.background
        c = [float(x) for x in b] + [1.0] * (4 - len(b))
        rgba = np.clip(np.round(np.asarray(c[:4], np.float64) * 255.0), 0, 255).astype(np.uint32)
        C = np.zeros((), CPARAMS_DTYPE)
        C["background"] = int(rgba[0] | (rgba[1] << 8) | (rgba[2] << 16) | (np.uint32(255) << 24))
        C["groups_x"], C["budget_on"] = gx, 1 if budget_on else 0
        C["pick_x0"], C["pick_y0"], C["pick_w"], C["pick_h"] = pick
        self.gpu.queue.write_buffer(self.cparams, 0, C.tobytes())

    # ------------------------------------------------------------------ frame
    def encode(self, enc: Any, plan: FramePlan) -> None:
        """Record the frame: clear, (budget passes), raster pass(es), resolve pass."""
        g = self.gpu
        var = self.variant(plan, g.cmode)
        self.write_cparams(plan.gx, plan.budget_on, (g.row_bytes // 4, 0, 0, 0))
        segs = plan.walk  # the point passes walk the runs that survive batch culling
        bgs = [self.groups(plan.set, seg) for seg in segs]
        enc.clear_buffer(self.keys)
        if not self.key64:
            enc.clear_buffer(self.ikeys)
        cp = enc.begin_compute_pass(**g.ts_writes(0))

        def each(name: str) -> None:  # one dispatch per segment, in logical order
            cp.set_pipeline(self._raster_pipe(name, var))
            for seg, bg in zip(segs, bgs):
                cp.set_bind_group(0, bg["raster"])
                cp.dispatch_workgroups(seg.gx, seg.gy, 1)

        if plan.budget_on:
            each("count")
            each("thin")
            cp.set_bind_group(0, bgs[0]["raster"])
            cp.set_pipeline(self._raster_pipe("scan", var))
            cp.dispatch_workgroups(1, 1, 1)
        for name in (("raster",) if self.key64 else ("raster", "index")):
            each(name)
        cp.end()
        cp = enc.begin_compute_pass(**g.ts_writes(2))
        cp.set_pipeline(self._resolve_pipe(g.cmode, var["RANGE_AUTO"]))
        for bg in (bgs if segs is plan.segments else [self.groups(plan.set, seg) for seg in plan.segments]):
            cp.set_bind_group(0, bg["resolve"])
            cp.dispatch_workgroups(math.ceil(g.width / 256), g.height, 1)
        cp.end()

    def copy_image(self, enc: Any, dst: Any) -> None:
        enc.copy_buffer_to_buffer(self.img, 0, dst, 0, dst.size)

    # ------------------------------------------------------------------ picking
    def pick_block(self, plan: FramePlan, x0: int, y0: int, bw: int, bh: int) -> tuple[np.ndarray, np.ndarray]:
        g = self.gpu
        n = bw * bh
        BU = g.wgpu.BufferUsage
        if self.pick_buf is None or self.pick_buf.size < n * 32:
            destroy_all([self.pick_buf])
            self.pick_buf = g.buffer(max(n, 1024) * 32, BU.STORAGE | BU.COPY_SRC, "pick-block")
        if "pick" not in self.pipes:  # (the gather needs no colour: the default variant)
            self.pipes["pick"] = g.compute_pipeline(self.bgl_resolve, self.resolve_files + ("pick.wgsl",), "main",
                                                    "pick")
        self.write_cparams(0, False, (x0, y0, bw, bh))
        enc = g.device.create_command_encoder()
        cp = enc.begin_compute_pass()
        cp.set_pipeline(self.pipes["pick"])
        for seg in plan.segments:
            cp.set_bind_group(0, g.bind(self.bgl_resolve, self._head(plan.set, seg)
                                        + [g.lut, g.rng, self.pick_buf, self.edl]))
            cp.dispatch_workgroups(math.ceil(n / 64), 1, 1)
        cp.end()
        g.queue.submit([enc.finish()])
        raw = g.queue.read_buffer(self.pick_buf, 0, n * 32)
        ids = np.frombuffer(raw, np.uint32).reshape(n, 8)[:, 0].reshape(bh, bw).copy()
        attrs = np.frombuffer(raw, np.float32).reshape(n, 8)[:, 1:5].reshape(bh, bw, 4).copy()
        return ids, attrs

    # ------------------------------------------------------------------ tests
    def survivors(self, plan: FramePlan) -> np.ndarray:
        """Logical indices that pass every test (and the thinning) in the last frame's
        parameters, capped at the budget, as slots."""
        g = self.gpu
        BU = g.wgpu.BufferUsage
        size = max(seg.logical_base + seg.size for seg in plan.segments)  # logical indices of the ring
        dbg = g.buffer(max(size, 1) * 4, BU.STORAGE | BU.COPY_SRC, "debug-flags")
        try:
            self.write_cparams(plan.gx, plan.budget_on)
            enc = g.device.create_command_encoder()
            cp = enc.begin_compute_pass()
            cp.set_pipeline(self._raster_pipe("debug", self.variant(plan, g.cmode)))
            for seg in plan.walk:  # (culled batches: flags stay 0)
                cp.set_bind_group(0, g.bind(self.bgl_raster, self._head(plan.set, seg)
                                            + [g.state_at(0), g.rng, self.wgc, dbg] + self._compact_bufs(plan.set, seg)))
                cp.dispatch_workgroups(seg.gx, seg.gy, 1)
            cp.end()
            g.queue.submit([enc.finish()])
            flags = np.frombuffer(g.queue.read_buffer(dbg, 0, max(size, 1) * 4), np.uint32)[:size]
        finally:
            dbg.destroy()
        logical = np.flatnonzero(flags == 1)
        if plan.budget_on:
            logical = logical[:max(int(plan.budget_n), 0)]
        return np.sort((plan.head + logical.astype(np.int64)) % max(plan.capacity, 1))

    def info(self) -> dict[str, Any]:
        return {"compute_keys": self.key_variant}  # (compact positions: the core's info)

    @property
    def key_variant(self) -> str:
        """The depth-key variant (deterministic either way)."""
        return "64-bit atomicMax" if self.key64 else "2x32-bit (depth pass, then index pass)"

    def close(self) -> None:
        destroy_all([self.dummy, self.keys, self.ikeys, self.wgc, self.dbg, self.cparams, self.pick_buf, self.img, self.edl])
        self.bg_cache.clear()
