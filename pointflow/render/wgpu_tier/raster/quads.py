"""The quads raster method (``render.raster: quads``): cull + compaction + indirect draw.

1. ``cull`` (one thread per logical index, workgroup 256): occupancy, finite, time window,
   6 frustum planes, LOD stride, importance sampling -> a keep flag and a count per
   workgroup; ``scan`` (one workgroup) turns the counts into offsets; ``emit`` writes the
   survivors in logical order as (slot, RGBA8 colour) + clip position, so the projection and
   colour are computed once per point, not once per quad vertex, and equal-depth ties resolve
   to the lower logical index; ``finalize`` writes the count into the ``drawIndirect``
   arguments (with a budget, ``thin``/``thin_scan``/``thin_emit`` + ``finalize_budget`` thin
   the survivors to the budget the same way);
2. ``draw_indirect`` of instanced quads (6 vertices per point) into an RGBA8 target with a
   depth buffer, one entry point per shape (``wgsl/draw.wgsl``).

A ring in several chunks (:mod:`..chunks`) runs steps 1 for every segment in logical order
(each segment's survivors land in its chunk's output buffers, a second segment of the same
chunk in a window after the first's), the budget steps after all of them (the thinning
fraction counts every segment's survivors, the hard cap runs on across segments), and one
indirect draw per segment in logical order, so ties still go to the lower logical index.

Picking re-draws the last frame's survivors into an id + attribute target under a scissor
of the (2r+1)^2 block around the cursor.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from .. import edl, sources
from ..chunks import OUT_ALIGN
from ..layout import Flag
from .base import FramePlan, RasterMethod, destroy_all

_EMIT_K = 8  # logical indices per thread in the emit pass (EMIT_K in cull.wgsl)
_CULL = ("common.wgsl", "scan.wgsl", "cull.wgsl")
_THIN = ("common.wgsl", "scan.wgsl", "thin.wgsl")
_DRAW = ("common.wgsl", "lut_colour.wgsl", "draw.wgsl")


class QuadsRaster(RasterMethod):
    name = "quads"
    points_per_group = 256
    slot_bytes = 16        # survivors' clip positions
    pad_slots = OUT_ALIGN  # a second segment's window starts aligned

    def __init__(self, gpu):
        super().__init__(gpu)
        g, wgpu = gpu, gpu.wgpu
        BU, TU, SS = wgpu.BufferUsage, wgpu.TextureUsage, wgpu.ShaderStage
        # per chunk: the survivors (slot in the chunk, RGBA8) and their clip positions
        # (+ OUT_ALIGN: a second segment's window, or the runs' windows after batch culling,
        # start aligned: chunks.runs keeps them within n + OUT_ALIGN)
        self.out_len = [n + OUT_ALIGN for _, n in g.chunks]
        self.idx1 = [g.buffer(n * 8, BU.STORAGE | BU.COPY_SRC, f"idx1.{c}") for c, n in enumerate(self.out_len)]
        self.clip1 = [g.buffer(n * 16, BU.STORAGE, f"clip1.{c}") for c, n in enumerate(self.out_len)]
        groups = (g.chunk_len + 255) // 256  # scratch of one segment at a time
        self.flags = g.buffer(groups * 256 * 4, BU.STORAGE, "keep-flags")          # per logical index
        self.wgc = g.buffer((groups + _EMIT_K) * 4, BU.STORAGE, "workgroup-counts")  # -> offsets (scan)
        self.idx2: list[Any] = []  # thinned survivors (made with the first budget)
        self.clip2: list[Any] = []
        self.bgl_cull = g.layout(["uniform"] + ["read"] * 4 + ["rw"] * 4 + ["read"] + ["rw"] * 3 + ["read"],
                                 SS.COMPUTE)
        self.bgl_thin = g.layout(["uniform", "read", "rw", "rw", "read", "rw", "rw", "rw", "rw"], SS.COMPUTE)
        # only the pick fragment shader reads storage (t_ingest, importance) and Params (slot_base)
        self.bgl_draw = g.layout(["uniform"] + ["read"] * 8, SS.VERTEX,
                                 {0: SS.VERTEX | SS.FRAGMENT, 2: SS.VERTEX | SS.FRAGMENT, 3: SS.VERTEX | SS.FRAGMENT})
        naive = g.naive_float32
        self.p = {e: g.compute_pipeline(self.bgl_cull, _CULL, e, NAIVE=naive)
                  for e in ("cull", "scan", "emit", "finalize", "finalize_budget")}
        self.p.update({e: g.compute_pipeline(self.bgl_thin, _THIN, e) for e in ("thin", "thin_scan", "thin_emit")})
        self.pl_draw = g.device.create_pipeline_layout(bind_group_layouts=[self.bgl_draw])
        self.shape = "round" if g.cfg.point_shape == "round" else "square"
        self.edl_on = bool(g.cfg.edl.enabled)
        self.world = g.cfg.point_size_space == "world"
        self.draw_mod = g.device.create_shader_module(code=sources.source(*_DRAW), label="draw")
        self.draw_cache: dict[bool, Any] = {}
        self.draw_pipeline(False)
        w, h = g.width, g.height
        TF = wgpu.TextureFormat
        sampled = TU.TEXTURE_BINDING if self.edl_on else 0
        self.color_tex = g.device.create_texture(size=(w, h, 1), format=TF.rgba8unorm,
                                                 usage=TU.RENDER_ATTACHMENT | TU.COPY_SRC | sampled, label="colour")
        self.color_view = self.color_tex.create_view()
        self.depth_tex = g.device.create_texture(size=(w, h, 1), format=TF.depth32float,
                                                 usage=TU.RENDER_ATTACHMENT, label="depth")
        self.depth_view = self.depth_tex.create_view()
        self.edl = self._create_edl() if self.edl_on else None
        self.pick_tex: dict[str, Any] = {}
        self.p_pick = None
        self.bg_cache: dict[Any, dict[str, Any]] = {}

    def _create_edl(self) -> dict[str, Any]:
        """Eye-dome lighting: a linear-depth target beside the colour, and the post pass
        (``wgsl/edl_post.wgsl``) writing the shaded image into a buffer at the readback pitch."""
        g = self.gpu
        wgpu, dev = g.wgpu, g.device
        TU, TF, SS, BU = wgpu.TextureUsage, wgpu.TextureFormat, wgpu.ShaderStage, wgpu.BufferUsage
        lin = dev.create_texture(size=(g.width, g.height, 1), format=TF.r32float,
                                 usage=TU.RENDER_ATTACHMENT | TU.TEXTURE_BINDING, label="linear-depth")
        tex = {"sample_type": wgpu.TextureSampleType.unfilterable_float, "view_dimension": "2d"}
        bgl = dev.create_bind_group_layout(entries=[
            {"binding": 0, "visibility": SS.COMPUTE, "texture": tex},
            {"binding": 1, "visibility": SS.COMPUTE, "texture": tex},
            {"binding": 2, "visibility": SS.COMPUTE, "buffer": {"type": wgpu.BufferBindingType.storage}},
            {"binding": 3, "visibility": SS.COMPUTE, "buffer": {"type": wgpu.BufferBindingType.uniform}}])
        E = edl.params(g.cfg.edl, g.width, g.height, g.row_bytes // 4)
        ubo = g.buffer(E.nbytes, BU.UNIFORM | BU.COPY_DST, "edl-params")
        g.queue.write_buffer(ubo, 0, E.tobytes())
        img = g.buffer(g.row_bytes * g.height, BU.STORAGE | BU.COPY_SRC, "edl-image")
        lin_view = lin.create_view()
        bg = g.bind(bgl, [self.color_view, lin_view, img, ubo])
        return {"tex": lin, "view": lin_view, "ubo": ubo, "img": img, "bg": bg,
                "pipe": g.compute_pipeline(bgl, ("edl.wgsl", "edl_post.wgsl"), "main", "edl")}

    # ------------------------------------------------------------------ pipelines
    def _render_pipeline(self, vs: str, fs: str, targets: list[str], colour_in_vs: bool) -> Any:
        wgpu, dev = self.gpu.wgpu, self.gpu.device
        consts = sources.constants(WORLD=self.world, COLOUR_IN_VS=colour_in_vs)
        return dev.create_render_pipeline(
            layout=self.pl_draw,
            vertex={"module": self.draw_mod, "entry_point": vs, "buffers": [], "constants": consts},
            primitive={"topology": wgpu.PrimitiveTopology.triangle_list, "cull_mode": wgpu.CullMode.none},
            depth_stencil={"format": wgpu.TextureFormat.depth32float, "depth_write_enabled": True,
                           "depth_compare": wgpu.CompareFunction.less},
            multisample={"count": 1},
            fragment={"module": self.draw_mod, "entry_point": fs, "targets": [{"format": t} for t in targets],
                      "constants": consts},
        )

    def draw_pipeline(self, colour_in_vs: bool) -> Any:
        """The draw pipeline (colour from the cull, or computed per vertex)."""
        p = self.draw_cache.get(colour_in_vs)
        if p is None:
            TF = self.gpu.wgpu.TextureFormat
            if self.edl_on:
                p = self._render_pipeline(f"vs_{self.shape}_edl", f"fs_{self.shape}_edl",
                                          [TF.rgba8unorm, TF.r32float], colour_in_vs)
            else:
                p = self._render_pipeline(f"vs_{self.shape}", f"fs_{self.shape}", [TF.rgba8unorm], colour_in_vs)
            self.draw_cache[colour_in_vs] = p
        return p

    def groups(self, s: int, budget: bool, seg: Any) -> dict[str, Any]:
        """Bind groups of buffer set ``s`` for segment ``seg``: its Params and state words, its
        chunk's data, and its window of the chunk's output buffers."""
        c, off = seg.chunk, seg.out_off
        key = (s, budget, seg.index, c, off)
        bg = self.bg_cache.get(key)
        if bg is None:
            g = self.gpu
            if len(self.bg_cache) > max(64, 4 * g.max_segments):  # windows move with the head and the culling
                self.bg_cache.clear()
            data, P, st, win = g.data(s, c), g.params_at(seg.index), g.state_at(seg.index), g.window
            idx1, clip1 = win(self.idx1[c], off, 8), win(self.clip1[c], off, 16)
            bg = {"cull": g.bind(self.bgl_cull, [P, *data, idx1, st, g.rng, g.dargs, g.lut, clip1, self.flags,
                                                 self.wgc, g.blod])}
            drawn_idx, drawn_clip = idx1, clip1
            if budget:
                if not self.idx2:
                    BU = g.wgpu.BufferUsage
                    self.idx2 = [g.buffer(n * 8, BU.STORAGE | BU.COPY_SRC, f"idx2.{i}") for i, n in enumerate(self.out_len)]
                    self.clip2 = [g.buffer(n * 16, BU.STORAGE, f"clip2.{i}") for i, n in enumerate(self.out_len)]
                idx2, clip2 = win(self.idx2[c], off, 8), win(self.clip2[c], off, 16)
                bg["thin"] = g.bind(self.bgl_thin, [P, idx1, idx2, st, clip1, clip2, self.flags, self.wgc, g.rng])
                drawn_idx, drawn_clip = idx2, clip2
            bg["draw"] = g.bind(self.bgl_draw, [P, *data, drawn_idx, g.lut, g.rng, drawn_clip])
            self.bg_cache[key] = bg
        return bg

    def _draws(self, rp: Any, plan: FramePlan) -> None:
        """One indirect draw per segment, in logical order (ties: the lower logical index)."""
        g = self.gpu
        for seg in plan.walk:
            rp.set_bind_group(0, self.groups(plan.set, plan.budget_on, seg)["draw"])
            rp.draw_indirect(g.state, seg.index * g.STATE_STRIDE)

    # ------------------------------------------------------------------ frame
    def encode(self, enc: Any, plan: FramePlan) -> None:
        g, wgpu, p = self.gpu, self.gpu.wgpu, self.p
        bgs = [self.groups(plan.set, plan.budget_on, seg) for seg in plan.walk]
        cp = enc.begin_compute_pass(**g.ts_writes(0))
        for seg, bg in zip(plan.walk, bgs):
            cp.set_bind_group(0, bg["cull"])
            cp.set_pipeline(p["cull"])
            cp.dispatch_workgroups(seg.gx, seg.gy, 1)
            cp.set_pipeline(p["scan"])
            cp.dispatch_workgroups(1, 1, 1)
            cp.set_pipeline(p["emit"])
            cp.dispatch_workgroups(math.ceil(seg.groups / _EMIT_K), 1, 1)
            if not plan.budget_on:
                cp.set_pipeline(p["finalize"])
                cp.dispatch_workgroups(1, 1, 1)
        if plan.budget_on:  # after every segment's cull: the fraction counts all survivors
            for bg in bgs:
                cp.set_bind_group(0, bg["cull"])
                cp.set_pipeline(p["finalize"])
                cp.dispatch_workgroups(1, 1, 1)
                cp.set_bind_group(0, bg["thin"])
                cp.set_pipeline(p["thin"])
                cp.dispatch_workgroups_indirect(g.dargs, 0)
                cp.set_pipeline(p["thin_scan"])
                cp.dispatch_workgroups(1, 1, 1)
                cp.set_pipeline(p["thin_emit"])
                cp.dispatch_workgroups_indirect(g.dargs, 0)
                cp.set_pipeline(p["finalize_budget"])
                cp.set_bind_group(0, bg["cull"])
                cp.dispatch_workgroups(1, 1, 1)
        cp.end()
        b = g.cfg.background
        targets = [{"view": self.color_view, "load_op": wgpu.LoadOp.clear, "store_op": wgpu.StoreOp.store,
                    "clear_value": (float(b[0]), float(b[1]), float(b[2]), 1.0)}]
        if self.edl is not None:  # linear depth, 0 = background
            targets.append({"view": self.edl["view"], "load_op": wgpu.LoadOp.clear, "store_op": wgpu.StoreOp.store,
                            "clear_value": (0.0, 0.0, 0.0, 0.0)})
        rp = enc.begin_render_pass(
            color_attachments=targets,
            depth_stencil_attachment={"view": self.depth_view, "depth_clear_value": 1.0,
                                      "depth_load_op": wgpu.LoadOp.clear, "depth_store_op": wgpu.StoreOp.store},
            **g.ts_writes(2))
        rp.set_pipeline(self.draw_pipeline(bool(int(plan.params["flags"]) & Flag.COLOUR_IN_VS)))
        self._draws(rp, plan)
        rp.end()
        if self.edl is not None:
            cp = enc.begin_compute_pass()
            cp.set_pipeline(self.edl["pipe"])
            cp.set_bind_group(0, self.edl["bg"])
            cp.dispatch_workgroups(math.ceil(g.width / 256), g.height, 1)
            cp.end()

    def copy_image(self, enc: Any, dst: Any) -> None:
        g = self.gpu
        if self.edl is not None:  # the EDL pass wrote the image with the readback's pitch
            enc.copy_buffer_to_buffer(self.edl["img"], 0, dst, 0, dst.size)
            return
        enc.copy_texture_to_buffer({"texture": self.color_tex, "mip_level": 0, "origin": (0, 0, 0)},
                                   {"buffer": dst, "offset": 0, "bytes_per_row": g.row_bytes,
                                    "rows_per_image": g.height}, (g.width, g.height, 1))

    # ------------------------------------------------------------------ picking
    def _ensure_pick(self) -> None:
        if self.pick_tex:
            return
        g = self.gpu
        TU, TF = g.wgpu.TextureUsage, g.wgpu.TextureFormat
        w, h = g.width, g.height
        self.p_pick = self._render_pipeline(f"vs_pick_{self.shape}", f"fs_pick_{self.shape}",
                                            [TF.r32uint, TF.rgba32float], False)
        ids = g.device.create_texture(size=(w, h, 1), format=TF.r32uint, usage=TU.RENDER_ATTACHMENT | TU.COPY_SRC)
        attrs = g.device.create_texture(size=(w, h, 1), format=TF.rgba32float, usage=TU.RENDER_ATTACHMENT | TU.COPY_SRC)
        depth = g.device.create_texture(size=(w, h, 1), format=TF.depth32float, usage=TU.RENDER_ATTACHMENT)
        self.pick_tex = {"ids": ids, "attrs": attrs, "depth": depth, "ids_view": ids.create_view(),
                         "attrs_view": attrs.create_view(), "depth_view": depth.create_view()}

    def pick_block(self, plan: FramePlan, x0: int, y0: int, bw: int, bh: int) -> tuple[np.ndarray, np.ndarray]:
        g, wgpu = self.gpu, self.gpu.wgpu
        self._ensure_pick()
        T = self.pick_tex
        enc = g.device.create_command_encoder()
        rp = enc.begin_render_pass(
            color_attachments=[
                {"view": T["ids_view"], "load_op": wgpu.LoadOp.clear, "store_op": wgpu.StoreOp.store,
                 "clear_value": (0, 0, 0, 0)},
                {"view": T["attrs_view"], "load_op": wgpu.LoadOp.clear, "store_op": wgpu.StoreOp.store,
                 "clear_value": (1.0, 0.0, 0.0, 0.0)}],
            depth_stencil_attachment={"view": T["depth_view"], "depth_clear_value": 1.0,
                                      "depth_load_op": wgpu.LoadOp.clear, "depth_store_op": wgpu.StoreOp.store})
        rp.set_scissor_rect(x0, y0, bw, bh)
        rp.set_pipeline(self.p_pick)
        self._draws(rp, plan)
        rp.end()
        row_ids = (bw * 4 + 255) // 256 * 256
        row_attr = (bw * 16 + 255) // 256 * 256
        BU = wgpu.BufferUsage
        b_ids = g.buffer(row_ids * bh, BU.MAP_READ | BU.COPY_DST, "pick-ids")
        b_attr = g.buffer(row_attr * bh, BU.MAP_READ | BU.COPY_DST, "pick-attrs")
        for tex, buf, row in ((T["ids"], b_ids, row_ids), (T["attrs"], b_attr, row_attr)):
            enc.copy_texture_to_buffer({"texture": tex, "mip_level": 0, "origin": (x0, y0, 0)},
                                       {"buffer": buf, "offset": 0, "bytes_per_row": row, "rows_per_image": bh},
                                       (bw, bh, 1))
        g.queue.submit([enc.finish()])
        try:
            b_ids.map_sync(wgpu.MapMode.READ)
            ids = np.frombuffer(b_ids.read_mapped(), np.uint32).reshape(bh, row_ids // 4)[:, :bw].copy()
            b_ids.unmap()
            b_attr.map_sync(wgpu.MapMode.READ)
            attrs = np.frombuffer(b_attr.read_mapped(), np.float32).reshape(bh, row_attr // 4)[:, :bw * 4]
            attrs = attrs.reshape(bh, bw, 4).copy()
            b_attr.unmap()
        finally:
            destroy_all([b_ids, b_attr])
        return ids, attrs

    # ------------------------------------------------------------------ tests
    def survivors(self, plan: FramePlan) -> np.ndarray:
        g = self.gpu
        st = np.frombuffer(g.queue.read_buffer(g.state), np.uint32).reshape(-1, g.STATE_STRIDE // 4)
        out = [np.zeros(0, np.int64)]
        for seg in plan.walk:
            n = int(st[seg.index, 1])
            if n:
                buf = (self.idx2 if plan.budget_on else self.idx1)[seg.chunk]
                idx = np.frombuffer(g.queue.read_buffer(buf, seg.out_off * 8, n * 8), np.uint32)[0::2]
                out.append(idx.astype(np.int64) + seg.slot_base)
        return np.sort(np.concatenate(out))

    def close(self) -> None:
        T, E = self.pick_tex, self.edl or {}
        destroy_all([E.get("tex"), E.get("ubo"), E.get("img"), *self.idx1, *self.idx2, *self.clip1, *self.clip2,
                     self.flags, self.wgc, self.color_tex, self.depth_tex, T.get("ids"), T.get("attrs"), T.get("depth")])
        self.pick_tex = {}
        self.bg_cache.clear()
