"""The per-frame ``Params`` record of the wgpu tier (layout: :data:`.layout.PARAMS`)."""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from ..config import RenderConfig
from ..base import FrameInput
from ..camera import Camera, planes_of
from .layout import NO_BUDGET, PARAMS_DTYPE, ColourMode, Flag
from .reference import budget_seed, seed_hash


def mat_cols(m: np.ndarray) -> np.ndarray:
    """float64 row-major 4x4 -> float32 column-major (WGSL mat4x4 layout)."""
    return np.ascontiguousarray(np.asarray(m, np.float64).T, dtype=np.float32).ravel()


def colour_range(cfg: RenderConfig, cmode: int, chan, frame: FrameInput) -> tuple[int, float, float, float]:
    """(flags, lo, hi, scale) for LUT colouring."""
    if cmode not in (ColourMode.SCALAR, ColourMode.Z, ColourMode.TIME):
        return 0, 0.0, 0.0, 0.0
    cr = cfg.color_range
    if isinstance(cr, (list, tuple)):
        lo, hi = float(cr[0]), float(cr[1])
        if cmode == ColourMode.Z:  # fixed range is in world z; positions are origin-relative
            lo, hi = lo - float(frame.origin[2]), hi - float(frame.origin[2])
    elif cmode == ColourMode.SCALAR and chan in frame.channel_ranges:
        lo, hi = (float(v) for v in frame.channel_ranges[chan])
    else:
        return Flag.RANGE_AUTO, 0.0, 0.0, 0.0
    if not hi > lo:
        return Flag.RANGE_DEGENERATE, lo, hi, 0.0
    return 0, lo, hi, float(np.float32(1.0 / (hi - lo)))


def importance_range(frame: FrameInput) -> tuple[float, float]:
    """Finite min/max over the occupied slots (the cadence normally sends this range)."""
    cap, size = int(frame.capacity), min(int(frame.capacity), int(frame.size))
    imp = frame.importance[:cap] if size == cap else frame.importance[frame.occupied_slots()]
    imp = imp[np.isfinite(imp)]
    return (float(imp.min()), float(imp.max())) if imp.size else (0.0, 0.0)


def depth_scale(camera: Camera) -> float:
    """2^-k with 2^k > far: the quads method's depth ``w * depth_scale`` is exact (a power of
    two) and below 1 for every point inside the far plane, so it orders like the linear view
    depth ``w`` with float32's full relative precision (unlike the hyperbolic ``z/w``)."""
    return float(2.0 ** -(math.floor(math.log2(max(float(camera.far), 1e-30))) + 1))


class ViewCache:
    """The camera's part of the Params record (matrices, frustum planes, scales) and the fixed
    colour, kept while they do not change: a still camera over a live ring, the common case,
    builds no matrix per frame (on the GPU the frame's CPU side is most of a 1M-point frame)."""

    __slots__ = ("key", "view", "colour_key", "colour")

    def __init__(self) -> None:
        self.key: Optional[tuple] = None
        self.view: tuple = ()
        self.colour_key: Optional[tuple] = None
        self.colour: Optional[np.ndarray] = None


def _view_block(camera: Camera, w: int, h: int, origin: np.ndarray, naive_float32: bool) -> tuple:
    """(vp, model as WGSL columns, float32 planes (6, 4), size_scale, depth_scale)."""
    if naive_float32:
        vp = camera.view_proj(w, h, None).astype(np.float32).astype(np.float64)
        model = np.eye(4)
        model[:3, 3] = origin.astype(np.float32)
        planes = camera.frustum_planes(w, h, origin)
    else:
        vp = camera.view_proj(w, h, origin)
        model = np.eye(4)
        planes = planes_of(vp)  # frustum_planes of the same matrix, not built a second time
    return (mat_cols(vp), mat_cols(model), planes.astype(np.float32).reshape(6, 4),
            camera.proj(w, h)[1, 1] * h / 2.0, depth_scale(camera))


def build(cfg: RenderConfig, frame: FrameInput, camera: Camera, w: int, h: int, cmode: int, chan,
          naive_float32: bool, n_slots: int, gx: int, groups: int,
          cache: Optional[ViewCache] = None) -> np.ndarray:
    """The Params record (a 0-d structured array) for this frame (``cache``: the view's part
    from the last frame when camera, size and origin are the same)."""
    P = np.zeros((), PARAMS_DTYPE)
    origin = np.asarray(frame.origin, np.float64)
    cache = cache if cache is not None else ViewCache()
    f64 = np.float64  # (a camera's arrays may have been replaced by lists since it was made)
    key = (np.asarray(camera.eye, f64).tobytes(), np.asarray(camera.target, f64).tobytes(),
           np.asarray(camera.up, f64).tobytes(), float(camera.fov_deg),
           float(camera.near), float(camera.far), int(w), int(h), origin.tobytes(), bool(naive_float32))
    if key != cache.key:
        cache.view, cache.key = _view_block(camera, w, h, origin, naive_float32), key
    P["vp"], P["model"], P["planes"], P["size_scale"], P["depth_scale"] = cache.view
    ckey = tuple(float(v) for v in cfg.color)
    if ckey != cache.colour_key:
        c = list(ckey) + [1.0] * (4 - len(ckey))
        cache.colour = np.round(np.clip(np.asarray(c[:4], np.float64), 0, 1) * 255.0) / 255.0
        cache.colour_key = ckey
    P["fixed_color"] = cache.colour
    P["vw"], P["vh"], P["point_size"] = w, h, cfg.point_size
    now = float(frame.now_ms)
    P["now_hi"] = now
    P["now_lo"] = now - float(np.float32(now))
    P["window_ms"] = cfg.time_window_ms
    flags = 0
    if cfg.time_window_ms > 0:
        flags |= Flag.WINDOW
    if cfg.importance_sampling:
        flags |= Flag.IMPORTANCE
        r = frame.channel_ranges.get("importance") or importance_range(frame)
        if not float(r[1]) > float(r[0]):
            flags |= Flag.IMP_DEGENERATE
        else:
            P["imp_lo"] = float(r[0])
            P["imp_scale"] = np.float32(1.0 / (float(r[1]) - float(r[0])))
    if cfg.point_size_space == "world":
        flags |= Flag.WORLD_SIZE
    if cfg.point_shape == "round":
        flags |= Flag.ROUND
    if cfg.lod_fill > 0:
        flags |= Flag.BATCH_LOD
    rflags, lo, hi, scale = colour_range(cfg, cmode, chan, frame)
    flags |= rflags
    if rflags & Flag.RANGE_AUTO:  # the range is reduced during the cull: colour in the draw
        flags |= Flag.COLOUR_IN_VS
    P["range_lo"], P["range_hi"], P["range_scale"] = lo, hi, scale
    P["head"] = int(frame.head) % max(frame.capacity, 1)
    P["size"] = min(int(frame.size), int(frame.capacity))
    P["capacity"] = int(frame.capacity)
    P["lod_stride"] = max(int(cfg.lod_stride), 1)
    P["seed"] = seed_hash(frame.frame_seed)
    P["budget_seed"] = budget_seed(frame.frame_seed)
    P["flags"] = int(flags)
    P["budget"] = NO_BUDGET if frame.budget is None else max(0, min(int(frame.budget), NO_BUDGET - 1))
    P["color_mode"] = int(cmode)
    P["groups_x"], P["n_slots"], P["groups_total"] = gx, n_slots, groups
    return P
