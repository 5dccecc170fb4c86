"""The OpenGL render tier (moderngl, EGL headless): for machines without a WebGPU adapter.

Culling, time window, LOD, importance sampling and budget run on the CPU with the same
vectorised rules as the cpu tier (:func:`pointflow.render.rules.select_points`), colours are
looked up there too (so they match bit for bit); then one instanced draw of the
survivors: 6 vertices per point expanded from ``gl_VertexID`` (no 64 px point-sprite cap),
projected on the GPU with the float32 cast of the float64 origin-relative matrix.

Rasterisation follows the shared rules exactly: the quad is drawn one pixel larger than the
point and the fragment shader keeps a pixel only when its centre passes the square
(``[p - s/2, p + s/2)``) or round (``<= s/2``) test, so GL's own edge rules never decide.
Nearer depth wins; survivors are drawn in *reverse* logical order with ``depth_func '<='``,
so at equal depth the lower logical index (drawn last) wins, as in the cpu tier, and a
point exactly on the far plane (depth 1.0 = the cleared depth) is still drawn.

Depth: the linear view depth (clip w) between the near and far planes, ``(w - near) /
(far - near)``, not the hyperbolic ``z / w``: the 24-bit depth buffer then resolves
``(far - near) / 2^24`` everywhere (0.4 mm with a far plane 7 km away), where ``z / w``
crowds its steps at the near plane and could not order a georeferenced map 5 km away
(camera.py sets near and far from what lies in front of the camera). The CPU has culled to
the frustum, so the depth is clamped to [0, 1] and GL clips nothing more.

Picking draws ``slot + 1`` into a second RGBA8 attachment (4 bytes) in the same pass.

Eye-dome lighting (``render.edl.enabled``): the draw also writes (log2 clip w, 1) of the
winning point into an RG32F attachment (cleared to 0 = background); a post pass over a
full-screen triangle applies :func:`pointflow.render.rules.edl_shade` with the offsets
from :func:`~pointflow.render.rules.edl_offsets` as uniforms, into a separate RGBA8 target
that :meth:`GlRenderer.read_image` reads. With EDL off none of this exists.
"""
from __future__ import annotations

import time
from typing import Any, Optional

import numpy as np

from .config import RenderConfig
from .base import FrameInput, FrameStats, Renderer, RenderError
from .batches import BatchBounds, culling_enabled
from .camera import Camera
from .rules import (EDL_NEIGHBOURS, EDL_SCALE, MAX_POINT_PX, drawn_attributes, edl_offsets, in_pick_circle,
                    pick_window, point_colors, resolve_pick, rgba_u8, select_points)

__all__ = ["GlRenderer", "GL_DEPTH_FIX"]

#: Maps WebGPU clip depth (0..w) to GL clip depth (-w..w): z' = 2 z - w.
GL_DEPTH_FIX = np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 2, -1], [0, 0, 0, 1]], np.float64)

_VERT = """
#version 330
uniform mat4 u_vp;          // GL_DEPTH_FIX @ view_proj (origin-relative), float32
uniform vec2 u_view;        // viewport (w, h) in pixels
uniform float u_size;       // screen: pixels; world: world units
uniform float u_world_k;    // world: P[1,1] * h / 2 (pixels per world unit at w = 1); 0 = screen
uniform vec2 u_depth;       // (near, 1 / (far - near)): window depth linear in the view depth w
in vec3 in_pos;
in vec4 in_color;
in uint in_slot;
flat out vec4 v_color;
flat out vec3 v_centre;     // (px, py) top-left origin, half size
flat out uint v_id;
#ifdef EDL
flat out float v_logz;      // log2 of the positive linear view depth (clip w)
#endif
const vec2 CORNERS[6] = vec2[](vec2(-1, -1), vec2(1, -1), vec2(1, 1), vec2(-1, -1), vec2(1, 1), vec2(-1, 1));
void main() {
    vec4 clip = u_vp * vec4(in_pos, 1.0);
    float s = u_world_k > 0.0 ? clamp(u_size * u_world_k / clip.w, 1.0, MAX_PX) : u_size;
    float h = 0.5 * s;
    vec2 ndc = clip.xy / clip.w;
    v_centre = vec3((ndc.x * 0.5 + 0.5) * u_view.x, (0.5 - ndc.y * 0.5) * u_view.y, h);
    vec2 off = CORNERS[gl_VertexID] * (h + 1.0) * 2.0 / u_view;  // one pixel of slack
    float dz = clamp((clip.w - u_depth.x) * u_depth.y, 0.0, 1.0);
    gl_Position = vec4((ndc + off) * clip.w, (2.0 * dz - 1.0) * clip.w, clip.w);
    v_color = in_color;
    v_id = in_slot + 1u;
#ifdef EDL
    v_logz = log2(clip.w);
#endif
}
"""

_FRAG = """
#version 330
uniform float u_height;
uniform int u_round;
flat in vec4 v_color;
flat in vec3 v_centre;
flat in uint v_id;
layout(location = 0) out vec4 f_color;
layout(location = 1) out vec4 f_id;  // slot + 1, little-endian bytes (exact in RGBA8)
#ifdef EDL
flat in float v_logz;
layout(location = 2) out vec2 f_logz;  // (log2 depth, 1 = covered)
#endif
void main() {
    vec2 c = vec2(gl_FragCoord.x, u_height - gl_FragCoord.y);  // pixel centre, top-left origin
    vec2 d = c - v_centre.xy;
    float h = v_centre.z;
    if (u_round == 1) {
        if (dot(d, d) > h * h) discard;
    } else if (d.x < -h || d.x >= h || d.y < -h || d.y >= h) {
        discard;
    }
    f_color = v_color;
    f_id = vec4(uvec4(v_id, v_id >> 8u, v_id >> 16u, v_id >> 24u) & 255u) / 255.0;
#ifdef EDL
    f_logz = vec2(v_logz, 1.0);
#endif
}
"""

_EDL_VERT = """
#version 330
void main() {  // one triangle covering the viewport
    vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
    gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}
"""

#: rules.edl_shade on the GPU: offsets arrive as integers (dy counts rows downward).
_EDL_FRAG = """
#version 330
uniform sampler2D u_color;
uniform sampler2D u_logz;          // (log2 depth, covered)
uniform ivec2 u_offsets[NEIGHBOURS];
uniform float u_k;                 // EDL_SCALE * strength / NEIGHBOURS
out vec4 f_color;
void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    vec4 c = texelFetch(u_color, p, 0);
    vec2 d = texelFetch(u_logz, p, 0).xy;
    if (d.y == 0.0) { f_color = c; return; }  // background: unchanged, no halo
    ivec2 size = textureSize(u_logz, 0);
    float sum = 0.0;
    for (int k = 0; k < NEIGHBOURS; k++) {
        ivec2 q = p + ivec2(u_offsets[k].x, -u_offsets[k].y);  // GL rows go up
        if (any(lessThan(q, ivec2(0))) || any(greaterThanEqual(q, size))) continue;
        vec2 n = texelFetch(u_logz, q, 0).xy;
        if (n.y != 0.0) sum += max(0.0, d.x - n.x);
    }
    // rounded here as the reference rounds (floor(c * shade + 0.5) in 8-bit steps), so the
    // framebuffer's own float -> unorm8 conversion (which rounds differently on NVIDIA than on
    // Mesa) only ever sees exact k/255 values
    f_color = vec4(floor(c.rgb * 255.0 * exp(-u_k * sum) + 0.5) / 255.0, c.a);
}
"""

_INSTANCE = np.dtype([("pos", "<f4", 3), ("color", "u1", 4), ("slot", "<u4")])


class GlRenderer(Renderer):
    """moderngl tier on a standalone EGL context (no display needed)."""

    tier = "gl"

    def __init__(self, cfg: RenderConfig, capacity: int, channels: list[str], *, backend: str = "egl"):
        super().__init__(cfg, capacity, channels)
        try:
            import moderngl
        except ImportError as exc:
            raise RenderError(f"moderngl is not installed: {exc}") from exc
        self._mgl = moderngl
        try:
            self.ctx = moderngl.create_standalone_context(backend=backend, require=330)
        except Exception as exc:  # noqa: BLE001 - EGL missing / no driver
            raise RenderError(f"no EGL OpenGL 3.3 context: {type(exc).__name__}: {exc}") from exc
        try:
            ctx = self.ctx
            edl = cfg.edl.enabled
            targets = self._make_targets(edl_pass=False)
            self._set_targets(targets)
            define = "#version 330\n#define EDL 1\n" if edl else "#version 330\n"
            self.prog = ctx.program(
                vertex_shader=_VERT.replace("MAX_PX", f"{MAX_POINT_PX:.1f}").replace("#version 330\n", define),
                fragment_shader=_FRAG.replace("#version 330\n", define))
            self._edl = self._edl_pass(self._logz_tex) if edl else None
        except RenderError:
            self.ctx.release()
            raise
        except Exception as exc:  # noqa: BLE001
            self.ctx.release()
            raise RenderError(f"GL set-up failed: {type(exc).__name__}: {exc}") from exc
        self._buf = None
        self._vao = None
        self._buf_points = 0
        self._bg = rgba_u8(cfg.background)
        self._last: dict[str, np.ndarray] = {}
        self.nonfinite_total = 0
        self.frames = 0
        self._bounds = BatchBounds() if culling_enabled() else None  # whole batches culled
        self._clear()

    def _make_targets(self, edl_pass: bool = True) -> tuple:
        """The framebuffers for the current size (colour, ids, depth, EDL pass)."""
        ctx = self.ctx
        W, H = self.width, self.height
        mx = ctx.info.get("GL_MAX_RENDERBUFFER_SIZE", 16384)
        if W > mx or H > mx:
            raise RenderError(f"viewport {W}x{H} exceeds GL_MAX_RENDERBUFFER_SIZE {mx}")
        edl = self.cfg.edl.enabled
        color = ctx.texture((W, H), 4) if edl else ctx.renderbuffer((W, H), 4)
        ids = ctx.renderbuffer((W, H), 4)  # slot + 1 as 4 little-endian bytes
        depth = ctx.depth_renderbuffer((W, H))
        extra = [ctx.texture((W, H), 2, dtype="f4")] if edl else []
        fbo = ctx.framebuffer(color_attachments=[color, ids, *extra], depth_attachment=depth)
        ids_fbo = ctx.framebuffer(color_attachments=[ids])
        self._logz_tex = extra[0] if edl else None
        return color, ids, depth, fbo, ids_fbo, (self._edl_pass(extra[0]) if edl and edl_pass else None), {}

    def _set_targets(self, t: tuple) -> None:
        self._color, self._ids, self._depth, self.fbo, self._ids_fbo, self._edl, self._last = t

    def resize(self, width: int, height: int) -> bool:
        """A set of framebuffers per size, kept for switching back (render/view/hub.py). The gl
        tier uploads the drawn points every frame anyway, so a view of another size costs
        its own upload as any gl frame does."""
        size, old = (int(width), int(height)), (self.width, self.height)
        if size == old:
            return True
        targets = self.__dict__.setdefault("_targets", {})
        targets[old] = (self._color, self._ids, self._depth, self.fbo, self._ids_fbo, self._edl, self._last)
        self.width, self.height = size
        if size in targets:
            self._set_targets(targets[size])
            return True
        try:
            self._set_targets(self._make_targets())
        except Exception:  # noqa: BLE001 - e.g. over GL_MAX_RENDERBUFFER_SIZE: the view gets the tier's size
            self.width, self.height = old
            self._set_targets(targets[old])
            return False
        self._clear()
        return True

    def _edl_pass(self, logz) -> dict[str, Any]:
        """The EDL post pass: program, empty vertex array, output target."""
        ctx = self.ctx
        prog = ctx.program(vertex_shader=_EDL_VERT,
                           fragment_shader=_EDL_FRAG.replace("NEIGHBOURS", str(EDL_NEIGHBOURS)))
        prog["u_offsets"].write(edl_offsets(self.cfg.edl.radius_px).astype("<i4").tobytes())
        prog["u_k"].value = EDL_SCALE * float(self.cfg.edl.strength) / EDL_NEIGHBOURS
        prog["u_color"].value = 0
        prog["u_logz"].value = 1
        out = ctx.renderbuffer((self.width, self.height), 4)
        return {"prog": prog, "vao": ctx.vertex_array(prog, []), "logz": logz,
                "logz_fbo": ctx.framebuffer(color_attachments=[logz]), "out": out,
                "fbo": ctx.framebuffer(color_attachments=[out])}

    def _ensure_buffer(self, n: int) -> None:
        if self._buf is not None and n <= self._buf_points:
            return
        cap = max(n, 1024, int(self._buf_points * 1.5))
        if self._vao is not None:
            self._vao.release()
            self._buf.release()
        self._buf = self.ctx.buffer(reserve=cap * _INSTANCE.itemsize)
        self._vao = self.ctx.vertex_array(
            self.prog, [(self._buf, "3f 4f1 1u /i", "in_pos", "in_color", "in_slot")])
        self._buf_points = cap

    def _clear(self) -> None:
        """Background + far depth; the id attachment to 0 (= no point). moderngl clears all
        colour attachments with one value, so the ids are cleared through their own fbo."""
        self.fbo.clear(*(self._bg.astype(np.float64) / 255.0), depth=1.0)
        self._ids_fbo.clear(0.0, 0.0, 0.0, 0.0)
        if self._edl is not None:
            self._edl["logz_fbo"].clear(0.0, 0.0, 0.0, 0.0)
        self.fbo.use()

    def render(self, frame: FrameInput, camera: Camera) -> FrameStats:
        t0 = time.perf_counter()
        W, H = self.width, self.height
        if self._bounds is not None:
            self._bounds.note(frame)
        sel = select_points(frame, camera, self.cfg, W, H, self._bounds)
        n = sel.n
        slots = sel.slots[::-1]  # newest first: with '<=' the lower logical index, drawn last, wins ties
        inst = np.empty(n, _INSTANCE)
        inst["pos"] = frame.positions[slots]
        inst["color"] = point_colors(frame, self.cfg, slots)
        inst["slot"] = slots.astype(np.uint32)
        t1 = time.perf_counter()
        try:
            ctx = self.ctx
            self._ensure_buffer(n)
            if n:
                self._buf.write(inst.tobytes())
            vp = (GL_DEPTH_FIX @ camera.view_proj(W, H, frame.origin)).astype(np.float32)
            self.prog["u_vp"].write(vp.T.tobytes())  # GLSL matrices are column-major
            self.prog["u_view"].value = (float(W), float(H))
            self.prog["u_depth"].value = (float(camera.near), float(1.0 / max(camera.far - camera.near, 1e-30)))
            self.prog["u_size"].value = float(self.cfg.point_size)
            world = self.cfg.point_size_space == "world"
            self.prog["u_world_k"].value = float(camera.proj(W, H)[1, 1] * H * 0.5) if world else 0.0
            self.prog["u_height"].value = float(H)
            self.prog["u_round"].value = 1 if self.cfg.point_shape == "round" else 0
            t2 = time.perf_counter()
            self.fbo.use()
            ctx.viewport = (0, 0, W, H)
            self._clear()
            ctx.enable_only(self._mgl.DEPTH_TEST)
            ctx.depth_func = "<="
            if n:
                self._vao.render(self._mgl.TRIANGLES, vertices=6, instances=n)
            if self._edl is not None:
                e = self._edl
                e["fbo"].use()
                ctx.enable_only(self._mgl.NOTHING)
                self._color.use(location=0)
                e["logz"].use(location=1)
                e["vao"].render(self._mgl.TRIANGLES, vertices=3)
            ctx.finish()
            err = ctx.error
            if err != "GL_NO_ERROR":
                raise RenderError(f"GL error after draw: {err}")
        except RenderError:
            raise
        except Exception as exc:  # noqa: BLE001 - a lost context surfaces as any exception
            raise RenderError(f"GL draw failed: {type(exc).__name__}: {exc}") from exc
        t3 = time.perf_counter()
        self._last = drawn_attributes(frame, sel.slots) if self.cfg.pick_strategy != "nearest" else {}
        self.nonfinite_total += sel.counts["nonfinite"]
        self.frames += 1
        ms = lambda a, b: (b - a) * 1e3
        return FrameStats(
            drawn=n, uploaded_bytes=n * _INSTANCE.itemsize,
            timings_ms={"select": ms(t0, t1), "upload": ms(t1, t2), "draw": ms(t2, t3), "total": ms(t0, t3)},
            extra={**{f"removed_{k}": v for k, v in sel.counts.items() if k not in ("occupied", "drawn")},
                   "nonfinite_total": self.nonfinite_total, "culled_points": sel.culled},
        )

    def read_image(self) -> np.ndarray:
        if self._edl is not None:
            raw = self._edl["fbo"].read(components=4, attachment=0, alignment=1)
        else:
            raw = self.fbo.read(components=4, attachment=0, alignment=1)
        img = np.frombuffer(raw, np.uint8).reshape(self.height, self.width, 4)
        return img[::-1].copy()  # GL rows start at the bottom

    def pick(self, x: float, y: float, pixel_ratio: float = 1.0) -> Optional[int]:
        win = pick_window(self.width, self.height, x, y, pixel_ratio, self.cfg.pick_radius)
        if win is None:
            return None
        X, Y, xa, xb, ya, yb = win
        # read only the block: GL's y axis points up
        raw = self.fbo.read(viewport=(xa, self.height - yb, xb - xa, yb - ya), components=4, attachment=1,
                            alignment=1)
        block = np.frombuffer(raw, "<u4").reshape(yb - ya, xb - xa)[::-1].astype(np.int64) - 1
        block = in_pick_circle(block, xa, ya, x, y, pixel_ratio, self.cfg.pick_radius)
        return resolve_pick(block, X - xa, Y - ya, self.cfg.pick_strategy, self._last)

    def info(self) -> dict[str, Any]:
        i = self.ctx.info
        return {"tier": self.tier, "size": [self.width, self.height], "renderer": i.get("GL_RENDERER"),
                "vendor": i.get("GL_VENDOR"), "version": i.get("GL_VERSION")}

    def close(self) -> None:
        ctx = getattr(self, "ctx", None)
        if ctx is not None:
            try:
                ctx.release()
            finally:
                self.ctx = None
