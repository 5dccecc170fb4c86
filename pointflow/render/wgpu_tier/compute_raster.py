"""The compute raster method of the wgpu tier (``render.raster: compute``).

Instead of compaction + an indirect instanced-quad draw, each frame is:

1. ``clear_buffer`` of the per-pixel key buffer (``W*H`` keys);
2. one pass over the occupied slots (workgroups of 256 threads, 16 points each, a
   workgroup covering 4096 consecutive logical indices; a 2-D grid beyond 65,535
   workgroups): every per-point test (occupancy, finite, time window, frustum incl. near,
   LOD stride, importance sampling, budget) fused with the projection and an atomic write
   of ``depth << 32 | logical`` into every pixel of the point's footprint (the rules of
   ``render/base.py``: square / round footprints of s px, world-size per point);
3. one pass per pixel resolving the winning key to its colour (single colour, rgb, scalar
   colormaps, z, ingest time; the auto range is reduced in pass 2) or the background, into
   the RGBA8 target through a storage texture.

The key and the deterministic variants are described in :mod:`.compute_shaders`: 64-bit
atomics where the adapter offers ``shader-int64-atomic-min-max``, else two 32-bit passes.
With a budget below the survivors two more passes count the survivors and the thinned
survivors per workgroup (a prefix sum gives each workgroup its first rank, so the hard cap
keeps the first b in logical order, as the cpu tier does).

Picking reads the key buffer of the last frame: a gather pass over the (2r+1)^2 block
under the cursor writes the winners' slots and attributes; no re-render.
"""
from __future__ import annotations

import json
import logging
import math
import os
from pathlib import Path
from typing import Any, Optional

import numpy as np

from . import compute_shaders as cs

log = logging.getLogger("pointflow.render.wgpu")

#: adapter features for the single-atomic 64-bit key
KEY64_FEATURES = ("shader-int64", "shader-int64-atomic-min-max")
#: ``auto`` uses the compute method for screen-size points up to this many pixels and from
#: this many ring slots per target pixel on (its per-pixel resolve is a fixed cost), unless
#: ``bench/bench_render.py --raster-crossover`` measured other limits (see :func:`crossover`)
DEFAULT_MAX_COMPUTE_PX = 8.0
DEFAULT_MIN_POINTS_PER_PIXEL = 0.02
ENV_RASTER = "POINTFLOW_RASTER"

_CX_WORDS = 8  # CParams


def raster_crossover_path() -> Path:
    return Path(__file__).resolve().parents[3] / "bench" / "results" / "raster_crossover.json"


def crossover() -> tuple[float, float, str]:
    """(largest screen point size in px at which compute measured faster than quads, smallest
    ring capacity per target pixel from which it did, where the numbers come from): the user
    cache, then the checkout's ``bench/results/raster_crossover.json``, then the defaults."""
    for p in (Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "pointflow" / "raster_crossover.json",
              raster_crossover_path()):
        try:
            d = json.loads(p.read_text())
            return float(d["max_compute_point_px"]), float(d["min_compute_points_per_pixel"]), str(p)
        except (OSError, ValueError, KeyError, TypeError):
            continue
    return DEFAULT_MAX_COMPUTE_PX, DEFAULT_MIN_POINTS_PER_PIXEL, "built-in default"


def choose_raster(cfg: Any, features: Any, key_bytes_needed: int, max_binding: int,
                  capacity: int = 0) -> tuple[str, str]:
    """("compute" | "quads", why) for ``render.raster`` (or env ``POINTFLOW_RASTER``)."""
    want = os.environ.get(ENV_RASTER, "").strip().lower() or cfg.raster
    src = f"${ENV_RASTER}={want}" if os.environ.get(ENV_RASTER, "").strip() else f"render.raster={want}"
    if want not in ("auto", "compute", "quads"):
        raise ValueError(f"{src}: expected auto, compute or quads")
    fits = key_bytes_needed <= max_binding
    if want == "quads":
        return "quads", f"{src}"
    if want == "compute":
        if not fits:
            raise ValueError(f"{src}: the per-pixel key buffer needs {key_bytes_needed} bytes, "
                             f"the device allows {max_binding} per storage buffer (render.size too large)")
        return "compute", src
    if not fits:
        return "quads", f"{src}: key buffer of {key_bytes_needed} bytes > device limit {max_binding}: quads"
    if cfg.point_size_space == "world":
        return "quads", (f"{src}: world-size points may cover up to 4096 px each; the compute method's cost "
                         "grows with the footprint area: quads")
    lim, ppp, where = crossover()
    if float(cfg.point_size) > lim:
        return "quads", (f"{src}: point_size {cfg.point_size} px > {lim:g} px, the largest size at which "
                         f"compute measured faster (from {where}): quads")
    px = int(cfg.size[0]) * int(cfg.size[1])
    if capacity < ppp * px:
        return "quads", (f"{src}: ring of {capacity} points < {ppp:g} points per pixel x {px} pixels, below "
                         f"which compute's per-pixel pass costs more than it saves (from {where}): quads")
    return "compute", (f"{src}: point_size {cfg.point_size} px <= {lim:g} px and {capacity} points >= "
                       f"{ppp:g} per pixel (from {where}): compute")


class ComputeRaster:
    """Pipelines and buffers of the compute method; driven by ``WgpuRenderer``."""

    def __init__(self, r: Any, key64: bool, max_groups: int):
        self.r = r
        self.key64 = bool(key64)
        self.max_groups = int(max_groups)
        wgpu, dev = r._wgpu, r.device
        BU = wgpu.BufferUsage
        W, H = r.width, r.height
        self.n_px = W * H
        self.k = cs.K  # points per thread (fixed when the pipelines are generated)
        self.keys = r._buf(self.n_px * (8 if self.key64 else 4), BU.STORAGE | BU.COPY_DST, "keys")
        self.ikeys = r._buf(16 if self.key64 else self.n_px * 4, BU.STORAGE | BU.COPY_DST, "index-keys")
        groups = self.groups_for(r.render_capacity)
        self.wgc = r._buf((groups + 1) * 4, BU.STORAGE, "workgroup-counts")
        self.dbg = r._buf(16, BU.STORAGE, "debug-flags")
        self.cparams = r._buf(_CX_WORDS * 4, BU.UNIFORM | BU.COPY_DST, "compute-params")
        self.pick_buf: Optional[Any] = None
        SS = wgpu.ShaderStage
        ro = {"type": wgpu.BufferBindingType.read_only_storage}
        rw = {"type": wgpu.BufferBindingType.storage}
        uni = {"type": wgpu.BufferBindingType.uniform}

        def layout(kinds):
            return dev.create_bind_group_layout(entries=[
                {"binding": i, "visibility": SS.COMPUTE, **k} for i, k in enumerate(kinds)])

        b = lambda k: {"buffer": k}  # noqa: E731
        self.bgl_raster = layout([b(uni), b(uni), b(ro), b(ro), b(ro), b(ro), b(rw), b(rw), b(rw), b(rw), b(rw), b(rw)])
        res = [b(uni), b(uni), b(ro), b(ro), b(ro), b(ro), b(ro), b(ro), b(ro), b(ro)]
        self.bgl_resolve = layout(res + [b(rw)])
        # the RGBA8 image, rows padded to the readback pitch: read_image copies it as is
        self.img = r._buf(r._row_bytes * H, BU.STORAGE | BU.COPY_SRC, "image")
        self.bgl_pick = layout(res + [b(rw)])

        def pipe(bgl, code, entry="main", label=""):
            mod = dev.create_shader_module(code=code, label=label)
            return dev.create_compute_pipeline(layout=dev.create_pipeline_layout(bind_group_layouts=[bgl]),
                                               compute={"module": mod, "entry_point": entry})

        # specialised per shape and size space (constants, so the splat loop carries no branch on them)
        self._shape = {"round_points": r.cfg.point_shape == "round", "world_size": r.cfg.point_size_space == "world"}
        self._variant: dict[str, Any] = {}
        self._lazy: dict[str, Any] = {}
        self._resolve_pipes: dict[bool, Any] = {}
        self._pipe_fn = pipe
        self._bg_cache: dict[Any, Any] = {}

    # ------------------------------------------------------------------ helpers
    def groups_for(self, n: int) -> int:
        return max(1, math.ceil(int(n) / (256 * self.k)))

    def grid(self, groups: int) -> tuple[int, int]:
        gx = min(groups, self.max_groups)
        return gx, math.ceil(groups / gx)

    def set_variant(self, window: bool, lod: bool, importance: bool, range_auto: bool) -> None:
        """Which per-point tests this frame runs: selects the specialised pipelines
        (compiled on first use)."""
        self._variant = {"window": bool(window), "lod": bool(lod), "importance": bool(importance),
                         "range_auto": bool(range_auto), "cmode": int(self.r._cmode)}

    def _pipe(self, name: str) -> Any:
        key = (name, tuple(sorted(self._variant.items())))
        p = self._lazy.get(key)
        if p is None:
            dev, naive = self.r.device, self.r.naive_float32
            mode = {"count": 0, "thin": 1, "scan": 1, "raster": 2, "index": 2, "debug": 3}[name]
            code = cs.raster_source(mode, self.key64, name == "index", naive, **self._shape, **self._variant,
                                    k=self.k)
            mod = dev.create_shader_module(code=code, label=name)
            p = dev.create_compute_pipeline(
                layout=dev.create_pipeline_layout(bind_group_layouts=[self.bgl_raster]),
                compute={"module": mod, "entry_point": "scan" if name == "scan" else "main"})
            self._lazy[key] = p
        return p

    def _bind(self, layout, res: list[Any]) -> Any:
        entries = []
        for i, x in enumerate(res):
            if hasattr(x, "size") and hasattr(x, "map_sync"):
                entries.append({"binding": i, "resource": {"buffer": x, "offset": 0, "size": x.size}})
            else:
                entries.append({"binding": i, "resource": x})
        return self.r.device.create_bind_group(layout=layout, entries=entries)

    def _data(self, s: int) -> list[Any]:
        S = self.r._sets[s]
        return [S["pos"], S["tms"], S["imp"], S["col"]]

    def groups(self, s: int) -> dict[str, Any]:
        g = self._bg_cache.get(s)
        if g is None:
            r = self.r
            head = [r._params, self.cparams, *self._data(s), self.keys, self.ikeys]
            g = {"raster": self._bind(self.bgl_raster, head + [r._state, r._rng, self.wgc, self.dbg]),
                 "resolve": self._bind(self.bgl_resolve, head + [r._lut, r._rng, self.img])}
            self._bg_cache[s] = g
        return g

    def write_cparams(self, gx: int, budget_on: bool, pick: tuple[int, int, int, int] = (0, 0, 0, 0)) -> None:
        bg = self.r.cfg.background
        c = [float(x) for x in bg] + [1.0] * (4 - len(bg))
        rgba = np.clip(np.round(np.asarray(c[:4], np.float64) * 255.0), 0, 255).astype(np.uint32)
        packed = int(rgba[0] | (rgba[1] << 8) | (rgba[2] << 16) | (np.uint32(255) << 24))
        self.r.queue.write_buffer(self.cparams, 0, np.array(
            [packed, gx, 1 if budget_on else 0, 0, *pick], np.uint32))

    # ------------------------------------------------------------------ frame
    def resolve_pipeline(self, range_auto: bool) -> Any:
        """The resolve variant for the tier's colour mode; ``range_auto``: the colour range
        is this frame's GPU reduction (no range in the config or the handoff)."""
        p = self._resolve_pipes.get(range_auto)
        if p is None:
            p = self._pipe_fn(self.bgl_resolve, cs.resolve_source(self.key64, cmode=self.r._cmode,
                                                                  range_auto=range_auto), label="resolve")
            self._resolve_pipes[range_auto] = p
        return p

    def encode(self, enc: Any, s: int, groups: int, budget_on: bool, ts: Optional[dict[str, Any]],
               range_auto: bool = False) -> None:
        """Record the frame: clear, (budget passes), raster pass(es), resolve pass."""
        r = self.r
        gx, gy = self.grid(groups)
        self.write_cparams(gx, budget_on, (r._row_bytes // 4, 0, 0, 0))
        g = self.groups(s)
        enc.clear_buffer(self.keys)
        if not self.key64:
            enc.clear_buffer(self.ikeys)
        kw = {}
        if ts is not None:
            kw["timestamp_writes"] = {"query_set": ts["qs"], "beginning_of_pass_write_index": 0,
                                      "end_of_pass_write_index": 1}
        cp = enc.begin_compute_pass(**kw)
        cp.set_bind_group(0, g["raster"])
        if budget_on:
            for name in ("count", "thin"):
                cp.set_pipeline(self._pipe(name))
                cp.dispatch_workgroups(gx, gy, 1)
            cp.set_pipeline(self._pipe("scan"))
            cp.dispatch_workgroups(1, 1, 1)
        for name in (("raster",) if self.key64 else ("raster", "index")):
            cp.set_pipeline(self._pipe(name))
            cp.dispatch_workgroups(gx, gy, 1)
        cp.end()
        if ts is not None:
            kw["timestamp_writes"] = {"query_set": ts["qs"], "beginning_of_pass_write_index": 2,
                                      "end_of_pass_write_index": 3}
        cp = enc.begin_compute_pass(**kw)
        cp.set_bind_group(0, g["resolve"])
        cp.set_pipeline(self.resolve_pipeline(range_auto))
        cp.dispatch_workgroups(math.ceil(r.width / 256), r.height, 1)
        cp.end()

    # ------------------------------------------------------------------ picking
    def pick_block(self, s: int, x0: int, y0: int, bw: int, bh: int) -> tuple[np.ndarray, np.ndarray]:
        """(ids = slot + 1 or 0, attrs = (depth, importance, t_hi, t_lo)) of the block's
        winners in the last frame, as the quads method's pick textures hold them."""
        r = self.r
        dev = r.device
        n = bw * bh
        BU = r._wgpu.BufferUsage
        if self.pick_buf is None or self.pick_buf.size < n * 32:
            if self.pick_buf is not None:
                self.pick_buf.destroy()
            self.pick_buf = r._buf(max(n, 1024) * 32, BU.STORAGE | BU.COPY_SRC, "pick-block")
            self._lazy.pop("pick-bg", None)
        if "pick" not in self._lazy:  # (the gather needs no colour: the default variant)
            mod = dev.create_shader_module(code=cs.resolve_source(self.key64, pick=True), label="pick")
            self._lazy["pick"] = dev.create_compute_pipeline(
                layout=dev.create_pipeline_layout(bind_group_layouts=[self.bgl_pick]),
                compute={"module": mod, "entry_point": "main"})
        self.write_cparams(0, False, (x0, y0, bw, bh))
        bg = self._bind(self.bgl_pick, [r._params, self.cparams, *self._data(s), self.keys, self.ikeys,
                                        r._lut, r._rng, self.pick_buf])
        enc = dev.create_command_encoder()
        cp = enc.begin_compute_pass()
        cp.set_pipeline(self._lazy["pick"])
        cp.set_bind_group(0, bg)
        cp.dispatch_workgroups(math.ceil(n / 64), 1, 1)
        cp.end()
        r.queue.submit([enc.finish()])
        raw = r.queue.read_buffer(self.pick_buf, 0, n * 32)
        ids = np.frombuffer(raw, np.uint32).reshape(n, 8)[:, 0].reshape(bh, bw).copy()
        attrs = np.frombuffer(raw, np.float32).reshape(n, 8)[:, 1:5].reshape(bh, bw, 4).copy()
        return ids, attrs

    # ------------------------------------------------------------------ tests
    def debug_keep(self, s: int, groups: int, size: int, budget_on: bool) -> np.ndarray:
        """Tests only: logical indices that pass every test (and the thinning) in the last
        frame's parameters; the caller applies the budget's hard cap."""
        r = self.r
        BU = r._wgpu.BufferUsage
        dbg = r._buf(max(size, 1) * 4, BU.STORAGE | BU.COPY_SRC, "debug-flags")
        head = [r._params, self.cparams, *self._data(s), self.keys, self.ikeys]
        bg = self._bind(self.bgl_raster, head + [r._state, r._rng, self.wgc, dbg])
        gx, gy = self.grid(groups)
        self.write_cparams(gx, budget_on)
        enc = r.device.create_command_encoder()
        cp = enc.begin_compute_pass()
        cp.set_bind_group(0, bg)
        cp.set_pipeline(self._pipe("debug"))
        cp.dispatch_workgroups(gx, gy, 1)
        cp.end()
        r.queue.submit([enc.finish()])
        flags = np.frombuffer(r.queue.read_buffer(dbg, 0, max(size, 1) * 4), np.uint32)[:size]
        dbg.destroy()
        return np.flatnonzero(flags == 1)

    def close(self) -> None:
        for b in (self.keys, self.ikeys, self.wgc, self.dbg, self.cparams, self.pick_buf, self.img):
            if b is not None:
                try:
                    b.destroy()
                except Exception:
                    pass
        self._bg_cache.clear()
