"""The draw rules every render tier follows, written once (float64/numpy reference).

Selection (occupancy, finite, time window, LOD, importance sampling, frustum, budget), the
random draws, colour ranges and colours, footprints, the pick circle and eye-dome lighting.
The cpu and gl tiers call these functions; the wgpu tier implements them in WGSL and is
tested against them (``wgpu_tier/reference.py`` is their per-slot form). No tier imports
another tier.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..arrays import finite_rows
from .config import RenderConfig
from . import colormap
from .base import FrameInput
from .batches import BATCH_SHIFT, BatchBounds
from .camera import Camera

__all__ = ["Selection", "check_frame", "select_points", "pcg", "pcg_hash", "seed_hash", "budget_seed", "uniform01",
           "keep_probability", "importance_range_for_budget", "budget_fraction", "rgba_u8", "color_values",
           "point_colors", "MAX_POINT_PX", "point_sizes_px", "footprint_box", "in_round_footprint", "pick_window",
           "in_pick_circle", "drawn_attributes", "resolve_pick", "EDL_NEIGHBOURS", "EDL_SCALE", "edl_offsets",
           "edl_shade", "apply_shade"]

#: World-size points are clamped to [1, MAX_POINT_PX] pixels (a point at the near plane
#: would otherwise cover an unbounded area; sub-pixel points would vanish).
MAX_POINT_PX = 4096.0
_U32 = np.uint32


# --------------------------------------------------------------------------- hashing
def _pcg(v: np.ndarray) -> np.ndarray:
    # PCG-RXS-M-XS 32 (Jarzynski & Olano 2020, "Hash Functions for GPU Rendering"), uint32 in/out.
    state = v * _U32(747796405) + _U32(2891336453)
    word = ((state >> ((state >> _U32(28)) + _U32(4))) ^ state) * _U32(277803737)
    return (word >> _U32(22)) ^ word


def pcg(v) -> np.ndarray:
    """The WGSL ``pcg(v)`` on any integers taken modulo 2^32 (vectorised, uint32 out)."""
    x = (np.asarray(v).astype(np.uint64) & np.uint64(0xFFFFFFFF)).astype(_U32)
    with np.errstate(over="ignore"):
        return _pcg(x)


def pcg_hash(index: np.ndarray | int, seed: int = 0) -> np.ndarray:
    """Per-point random uint32 shared by every tier (the WGSL twin must match bit for bit)::

        fn pcg(v: u32) -> u32 {
            let state = v * 747796405u + 2891336453u;
            let word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
            return (word >> 22u) ^ word;
        }
        fn pcg_hash(index: u32, seed: u32) -> u32 { return pcg(index ^ pcg(seed)); }

    ``index`` is the ring *slot* (stable while a point lives, so sampling does not flicker
    as the head moves); ``seed`` is the frame seed, both taken modulo 2^32. Same as the
    wgpu tier's ``pcg(slot ^ seed_hash(seed))``.
    Test vectors: pcg_hash(0, 0) = 817759070, pcg_hash(1, 7) = 2809854175.
    """
    idx = np.atleast_1d(np.asarray(index)).astype(np.int64) & 0xFFFFFFFF
    s = _pcg(np.array([int(seed) & 0xFFFFFFFF], dtype=_U32))
    with np.errstate(over="ignore"):
        return _pcg(idx.astype(_U32) ^ s)


def seed_hash(frame_seed: int) -> int:
    """Per-frame seed of the importance draw: ``pcg(frame_seed)``."""
    return int(_pcg(np.array([int(frame_seed) & 0xFFFFFFFF], _U32))[0])


def budget_seed(frame_seed: int) -> int:
    """Per-frame seed of the budget thinning: ``pcg(seed_hash(frame_seed) ^ 0x9E3779B9)``."""
    return int(_pcg(np.array([seed_hash(frame_seed) ^ 0x9E3779B9], _U32))[0])


def uniform01(slots: np.ndarray, hashed_seed: int) -> np.ndarray:
    """float32 draw in [0, 1): ``(pcg(slot ^ hashed_seed) >> 8) * 2^-24`` (exact in float32)."""
    v = (np.asarray(slots).astype(np.int64) & 0xFFFFFFFF).astype(_U32) ^ _U32(hashed_seed & 0xFFFFFFFF)
    with np.errstate(over="ignore"):
        return (_pcg(v) >> _U32(8)).astype(np.float32) * np.float32(2.0 ** -24)


def keep_probability(importance: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Normalised importance in float32: ``clip((v - lo) * (1 / (hi - lo)), 0, 1)``;
    1.0 everywhere when the range is degenerate (``hi <= lo``: all-equal or all-zero
    importance carries no information, so nothing is sampled away); NaN → 0."""
    v = np.asarray(importance, np.float32)
    if not hi > lo:
        return np.ones(v.shape, np.float32)
    p = np.clip((v - np.float32(lo)) * np.float32(1.0 / (hi - lo)), np.float32(0), np.float32(1))
    p[~np.isfinite(p)] = 0
    return p


def importance_range_for_budget(importance: np.ndarray, lo: float, hi: float, budget: int) -> tuple[float, float]:
    """An importance range (lo, hi') that makes the expected number of sampled points equal
    ``budget``: with p = normalised importance, sampling keeps ``min(1, k p)`` in expectation,
    and ``hi' = lo + (hi - lo) / k`` does exactly that through the ordinary rule, in every
    tier. k is found by bisection (40 vectorised steps). Without this, sampling keeps about
    ``sum(p)`` points whatever the budget (a budget above that has no effect)."""
    p = keep_probability(importance, lo, hi).astype(np.float64)
    if not hi > lo or budget >= np.count_nonzero(p > 0):
        return (lo, lo + (hi - lo) * 1e-6) if hi > lo else (lo, hi)
    a, b = 1e-6, 1e6
    for _ in range(40):
        k = np.sqrt(a * b)
        if np.minimum(1.0, p * k).sum() < budget:
            a = k
        else:
            b = k
    return lo, lo + (hi - lo) / b


def budget_fraction(budget: int, survivors: int) -> np.float32:
    """Keep probability of a survivor under a budget b < n survivors, in float32 as on the
    GPU: ``max(b - 3 sqrt(b), b / 2) / n`` (aiming three standard deviations under b, so the
    hard cap rarely bites); 2 (keep all) when ``n <= b``."""
    if survivors <= budget:
        return np.float32(2.0)
    fb = np.float32(budget)
    return np.float32(max(fb - np.float32(3.0) * np.sqrt(fb), np.float32(0.5) * fb)) / np.float32(survivors)


# --------------------------------------------------------------------------- selection
@dataclass
class Selection:
    """Survivors of the per-frame filters, in ascending logical order."""

    logical: np.ndarray          # int64 logical indices (0 = oldest)
    slots: np.ndarray            # int64 ring slots
    counts: dict[str, int] = field(default_factory=dict)  # removed per filter + occupied/drawn
    culled: int = 0              # points in whole batches culled before any point was read

    @property
    def n(self) -> int:
        return int(self.slots.size)


def _finite_range(v: np.ndarray) -> tuple[float, float]:
    v = v[np.isfinite(v)]
    if v.size == 0:
        return 0.0, 0.0
    return float(v.min()), float(v.max())


def check_frame(frame: FrameInput) -> tuple[int, int]:
    """(capacity, size) after checking the arrays agree; a clear ValueError otherwise."""
    cap = int(frame.capacity)
    pos = frame.positions
    if cap < 1:
        raise ValueError(f"FrameInput.capacity must be >= 1, got {cap}")
    if pos.ndim != 2 or pos.shape[1] != 3 or pos.shape[0] < cap:
        raise ValueError(f"FrameInput.positions: expected ({cap}, 3), got {pos.shape}")
    for name, arr in (("importance", frame.importance), ("t_ingest_ms", frame.t_ingest_ms)):
        if arr.shape[0] < cap:
            raise ValueError(f"FrameInput.{name}: expected {cap} entries, got {arr.shape[0]}")
    size = int(frame.size)
    if not 0 <= size <= cap:
        raise ValueError(f"FrameInput.size must be in 0..capacity ({cap}), got {size}")
    return cap, size


def select_points(frame: FrameInput, camera: Camera, cfg: RenderConfig, width: int, height: int,
                  bounds: Optional[BatchBounds] = None) -> Selection:
    """Apply, in order: finite positions, time window (``now - t <= window``, off when 0),
    LOD stride (``logical % stride == 0``), footprint LOD (``render.lod_fill``: ``slot &
    mask == 0``, the slot's batch's mask from :func:`pointflow.render.batches.lod_masks`), importance sampling (``uniform01(slot,
    seed_hash(seed)) <= p`` in float32, p from :func:`keep_probability` over the
    ``importance`` range), frustum (all six planes ``>= 0``, float64, a point on a plane is
    kept), and the budget, only when survivors n > budget b: keep iff ``uniform01(slot,
    budget_seed(seed)) < max(b - 3 sqrt(b), b / 2) / n`` (float32), then at most the first
    b in logical order.
    The wgpu tier applies the same rules on the GPU (``wgpu_tier/reference.py`` is their
    per-slot form) except that the GPU's final truncation picks an arbitrary b.

    With ``bounds`` (:class:`pointflow.render.batches.BatchBounds`, noted for this frame),
    whole batches outside the frustum are skipped before any point is read: the same
    survivors, their points counted as ``nonfinite`` (the batch's count) and ``frustum``."""
    cap, size = check_frame(frame)
    counts = {"occupied": size, "nonfinite": 0, "time_window": 0, "lod": 0, "sampled": 0, "frustum": 0,
              "budget": 0}
    planes = camera.frustum_planes(width, height, frame.origin)
    cut = bounds.survivors(frame, planes) if bounds is not None and size else None
    if cut is None:
        logical = np.arange(size, dtype=np.int64)
    else:
        logical, culled_bad, culled = cut
        counts["nonfinite"], counts["frustum"] = culled_bad, culled - culled_bad
    slots = (int(frame.head) + logical) % cap
    pos = frame.positions[slots]
    keep = finite_rows(pos)
    counts["nonfinite"] += int(logical.size - np.count_nonzero(keep))
    if cfg.time_window_ms > 0:
        t = np.asarray(frame.t_ingest_ms[slots], np.float64)
        tw = (float(frame.now_ms) - t) <= float(cfg.time_window_ms)
        counts["time_window"] = int(np.count_nonzero(keep & ~tw))
        keep &= tw
    if cfg.lod_stride > 1:
        lod = (logical % int(cfg.lod_stride)) == 0
        counts["lod"] = int(np.count_nonzero(keep & ~lod))
        keep &= lod
    if cfg.lod_fill > 0 and size:
        bb = bounds  # the batches every tier thins by (BATCH_SHIFT: the compiled and GPU tests shift)
        if bb is None or bb.batch != 1 << BATCH_SHIFT:
            bb = BatchBounds(1 << BATCH_SHIFT)
            bb.note(frame)
        masks = bb.lod_masks(frame, camera, cfg, width, height)
        lod = (slots & masks[slots // bb.batch].astype(np.int64)) == 0
        counts["lod"] += int(np.count_nonzero(keep & ~lod))
        keep &= lod
    if cfg.importance_sampling:
        lo, hi = frame.channel_ranges.get("importance") or _finite_range(
            frame.importance[slots if cut is None else frame.occupied_slots()])  # the range: every point
        idx = np.flatnonzero(keep)
        p = keep_probability(frame.importance[slots[idx]], lo, hi)
        u = uniform01(slots[idx], seed_hash(frame.frame_seed))
        drop = idx[~(u <= p)]
        counts["sampled"] = int(drop.size)
        keep[drop] = False
    idx = np.flatnonzero(keep)
    if idx.size:
        d = pos[idx].astype(np.float64) @ planes[:, :3].T + planes[:, 3]
        inside = (d >= 0.0).all(axis=1)
        counts["frustum"] += int(idx.size - np.count_nonzero(inside))
        idx = idx[inside]
    if frame.budget is not None and idx.size > max(int(frame.budget), 0):
        b = max(int(frame.budget), 0)
        before = idx.size  # the thinned set depends only on the hash, then the oldest b
        idx = idx[uniform01(slots[idx], budget_seed(frame.frame_seed)) < budget_fraction(b, idx.size)][:b]
        counts["budget"] = int(before - idx.size)
    counts["drawn"] = int(idx.size)
    return Selection(logical=logical[idx], slots=slots[idx], counts=counts, culled=0 if cut is None else cut[2])


# --------------------------------------------------------------------------- colour ranges & colours
def rgba_u8(c) -> np.ndarray:
    """Config colour (3 or 4 floats in [0, 1]) → RGBA uint8 (``round(c * 255)``, alpha 255)."""
    v = [float(x) for x in c] + ([1.0] if len(c) == 3 else [])
    return np.clip(np.round(np.asarray(v, np.float64) * 255.0), 0, 255).astype(np.uint8)


def color_values(frame: FrameInput, cfg: RenderConfig, slots: np.ndarray, all_slots: Optional[np.ndarray] = None):
    """(values at ``slots``, (lo, hi)) for ``cfg.color_by``, or None for a single colour.

    ``z``/``height`` use the float32 offset and shift the range by the origin (so large
    coordinates keep their colour precision); the automatic range is the handoff's
    ``channel_ranges`` entry when present, else the finite min/max over the occupied slots
    whose position is finite (as the wgpu cull computes it)."""
    cb = cfg.color_by
    if cb in (None, "none", "rgb"):
        return None
    shift = 0.0
    if cb in ("z", "height"):
        src = frame.positions[:, 2]
        shift = float(frame.origin[2])
    elif cb == "ingest_time":
        src = frame.t_ingest_ms
    elif cb in frame.channels:
        src = frame.channels[cb]
        if src.ndim != 1:
            return None
    else:
        return None
    if isinstance(cfg.color_range, list):
        lo, hi = float(cfg.color_range[0]), float(cfg.color_range[1])
    elif cb in frame.channel_ranges:
        lo, hi = (float(x) for x in frame.channel_ranges[cb])
    else:
        occ = frame.occupied_slots() if all_slots is None else all_slots
        occ = occ[finite_rows(frame.positions[occ])]
        lo, hi = _finite_range(np.asarray(src[occ], np.float64) + shift)
    return np.asarray(src[slots]), (lo - shift, hi - shift)


def point_colors(frame: FrameInput, cfg: RenderConfig, slots: np.ndarray) -> np.ndarray:
    """(n, 4) uint8 RGBA of the points at ``slots``: rgb channel, colormap of a scalar
    (NaN → ``cfg.color``) or the single ``cfg.color``."""
    n = slots.size
    single = rgba_u8(cfg.color)
    if cfg.color_by == "rgb" and "rgb" in frame.channels:
        out = np.empty((n, 4), np.uint8)
        out[:, :3] = frame.channels["rgb"][slots]
        out[:, 3] = 255
        return out
    cv = color_values(frame, cfg, slots)
    if cv is None:
        return np.broadcast_to(single, (n, 4)).copy()
    values, (lo, hi) = cv
    bad = ~np.isfinite(values)
    if bad.any():  # lut_index maps NaN to -1 too, but casts it first (a RuntimeWarning)
        values = np.where(bad, np.float32(lo if np.isfinite(lo) else 0.0), values)
    idx = colormap.lut_index(values, lo, hi)
    idx[bad] = -1
    out = colormap.lut(cfg.colormap)[np.maximum(idx, 0)]
    out[idx < 0] = single
    return out


# --------------------------------------------------------------------------- footprints
def point_sizes_px(cfg: RenderConfig, camera: Camera, width: int, height: int, w: np.ndarray) -> np.ndarray | float:
    """Point size in pixels: constant (``screen``), or the projected height of a world
    length ``point_size`` at clip w (``world``: ``size * P[1,1] * height / 2 / w``),
    clamped to [1, MAX_POINT_PX]."""
    if cfg.point_size_space != "world":
        return float(cfg.point_size)
    f = camera.proj(width, height)[1, 1]
    with np.errstate(divide="ignore"):
        s = float(cfg.point_size) * f * height * 0.5 / w
    return np.clip(s, 1.0, MAX_POINT_PX)


def footprint_box(px: np.ndarray, py: np.ndarray, half, round_: bool, width: int, height: int):
    """(x0, x1, y0, y1) int64 pixel box [x0, x1) x [y0, y1), clipped to the image, of the
    pixels a point may cover. A square point of size s = 2 half covers the pixels whose
    centres c lie in ``[p - s/2, p + s/2)``; a round one those with ``|c - p| <= s/2``
    (test each pixel of the box with :func:`in_round_footprint`)."""
    x0 = np.ceil(px - half - 0.5)
    y0 = np.ceil(py - half - 0.5)
    if round_:
        x1 = np.floor(px + half - 0.5) + 1
        y1 = np.floor(py + half - 0.5) + 1
    else:
        x1 = np.ceil(px + half - 0.5)
        y1 = np.ceil(py + half - 0.5)
    clip = lambda v, hi: np.clip(v, 0, hi).astype(np.int64)
    return clip(x0, width), clip(x1, width), clip(y0, height), clip(y1, height)


def in_round_footprint(X, Y, px, py, half):
    """True where pixel (X, Y)'s centre lies within ``half`` of (px, py) (``<=``)."""
    dx = X + 0.5 - px
    dy = Y + 0.5 - py
    return dx * dx + dy * dy <= half * half


# --------------------------------------------------------------------------- picking
def pick_window(width: int, height: int, x: float, y: float, pixel_ratio: float, radius: int):
    """(X, Y, xa, xb, ya, yb): the framebuffer pixel under window (x, y) × pixel_ratio and
    the square block within ``radius`` × pixel_ratio around it (the radius is in logical
    pixels, as in the wgpu tier) clipped to the viewport; None when empty. Only the pixels
    of the block inside the circle count (:func:`in_pick_circle`)."""
    X, Y = int(np.floor(x * pixel_ratio)), int(np.floor(y * pixel_ratio))
    r = int(np.ceil(radius * pixel_ratio))
    xa, xb, ya, yb = max(X - r, 0), min(X + r + 1, width), max(Y - r, 0), min(Y + r + 1, height)
    if xa >= xb or ya >= yb:
        return None
    return X, Y, xa, xb, ya, yb


def in_pick_circle(block: np.ndarray, xa: int, ya: int, x: float, y: float, pixel_ratio: float,
                   radius: float) -> np.ndarray:
    """``block`` (from :func:`pick_window`) with -1 outside the pick circle: a pixel counts
    when its centre lies within ``radius`` × pixel_ratio of the cursor (x, y) × pixel_ratio,
    the rule of every tier (the wgpu tier's ``resolve_pick``); below half a pixel only the
    pixel under the cursor."""
    px, py = x * pixel_ratio, y * pixel_ratio
    r = float(radius) * pixel_ratio
    bh, bw = block.shape
    xx = np.arange(xa, xa + bw) + 0.5 - px
    yy = np.arange(ya, ya + bh) + 0.5 - py
    if r < 0.5:
        m = (np.floor(xx + px)[None, :] == np.floor(px)) & (np.floor(yy + py)[:, None] == np.floor(py))
    else:
        m = yy[:, None] ** 2 + xx[None, :] ** 2 <= r * r + 1e-9
    return np.where(m, block, -1)


def drawn_attributes(frame: FrameInput, slots: np.ndarray) -> dict[str, np.ndarray]:
    """Sorted drawn slots with their importance and ingest time (the slab is released after
    the frame, so pick strategies keep their own copy)."""
    s = np.sort(slots)
    return {"slots": s, "importance": np.asarray(frame.importance[s], np.float64),
            "t": np.asarray(frame.t_ingest_ms[s], np.float64)}


def resolve_pick(block: np.ndarray, cx: int, cy: int, strategy: str, last: dict[str, np.ndarray]) -> Optional[int]:
    """Choose among the slots in ``block`` ((h, w) int, -1 = empty) around block pixel
    (cx, cy): ``nearest`` pixel centre; ``highest_importance`` / ``recent_first`` among all
    in reach. Ties: smaller screen distance, then the lower slot."""
    jj, ii = np.nonzero(block >= 0)
    if jj.size == 0:
        return None
    slots = block[jj, ii].astype(np.int64)
    d2 = (ii - cx) ** 2 + (jj - cy) ** 2
    keys: list[np.ndarray] = [slots, d2]
    if strategy != "nearest" and last.get("slots") is not None and last["slots"].size:
        at = np.clip(np.searchsorted(last["slots"], slots), 0, last["slots"].size - 1)
        keys.append(-(last["importance"] if strategy == "highest_importance" else last["t"])[at])
    return int(slots[np.lexsort(keys)[0]])


# --------------------------------------------------------------------------- eye-dome lighting
#: EDL samples this many neighbours, at angles k * 2pi / 8.
EDL_NEIGHBOURS = 8
#: ``shade = exp(-EDL_SCALE * strength * response)`` (Potree's constant).
EDL_SCALE = 300.0


def edl_offsets(radius_px: float) -> np.ndarray:
    """(8, 2) int32 pixel offsets (dx, dy) of the EDL neighbours: for k = 0..7,
    ``(round(r cos(k pi/4)), round(r sin(k pi/4)))`` with Python's ``round`` (half to even).
    Computed once on the CPU; shaders receive these integers and never recompute them, so
    every tier samples the same pixels. dy counts image rows downward (the set is symmetric
    under a flip, so the sign convention does not change the sum)."""
    r = float(radius_px)
    return np.array([(round(r * math.cos(k * math.pi / 4)), round(r * math.sin(k * math.pi / 4)))
                     for k in range(EDL_NEIGHBOURS)], np.int32)


def edl_shade(log_depth: np.ndarray, covered: np.ndarray, offsets: np.ndarray, strength: float) -> np.ndarray:
    """(h, w) float64 EDL shade in (0, 1] of an image whose covered pixels have
    ``log_depth`` = log2 of the winning point's positive linear view depth.

    For a covered pixel p: ``response = (1/8) sum_k max(0, d(p) - d(p + o_k))``, where a
    neighbour that is background or outside the image contributes 0; ``shade =
    exp(-300 * strength * response)``. Background pixels get 1 (no halo)."""
    covered = np.asarray(covered, bool)
    h, w = covered.shape
    # background depth +inf: max(0, d - inf) = 0 for a covered pixel's background neighbour;
    # background pixels themselves get response 0 below, whatever their sum
    d = np.where(covered, np.asarray(log_depth, np.float64), np.inf)
    resp = np.zeros((h, w), np.float64)
    for dx, dy in np.asarray(offsets, np.int64).reshape(-1, 2):
        dx, dy = int(dx), int(dy)
        if abs(dx) >= w or abs(dy) >= h:
            continue  # every neighbour outside the image
        # pixels p whose neighbour p + (dx, dy) lies inside the image, and those neighbours
        py = slice(max(0, -dy), h - max(0, dy))
        px = slice(max(0, -dx), w - max(0, dx))
        qy = slice(max(0, dy), h - max(0, -dy))
        qx = slice(max(0, dx), w - max(0, -dx))
        with np.errstate(invalid="ignore"):  # inf - inf on the background: discarded below
            resp[py, px] += np.maximum(0.0, d[py, px] - d[qy, qx])
    resp[~covered] = 0.0  # background: shade exp(0) = 1, no halo
    resp /= EDL_NEIGHBOURS
    return np.exp(-EDL_SCALE * float(strength) * resp)


def apply_shade(image: np.ndarray, shade: np.ndarray) -> np.ndarray:
    """(h, w, 4) uint8 with RGB multiplied by ``shade`` and rounded to nearest
    (``floor(c * shade + 0.5)``, as a unorm8 render target stores it); alpha unchanged.
    A shade of exactly 1 leaves the colour byte-identical."""
    out = image.copy()
    rgb = np.floor(image[..., :3].astype(np.float64) * shade[..., None] + 0.5)
    out[..., :3] = np.clip(rgb, 0, 255).astype(np.uint8)
    return out
