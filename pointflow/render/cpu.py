"""The numpy render tier: the deterministic float64 reference every other tier is measured against.

Per frame (all vectorised numpy, no Python loops over points):

1. :func:`select_points` — occupancy, finite positions, time window, LOD stride, importance
   sampling, frustum, budget (shared with the gl tier, so both draw the same survivors).
2. Projection of the survivors in float64 with ``camera.view_proj(w, h, origin)``.
3. A z-buffered splat: each point covers the pixels of the rasterisation rules in
   :mod:`pointflow.render.base`; nearer depth wins, ties go to the lower logical index.
   Points are ranked once by (depth, logical index); every pixel keeps its lowest rank.
4. Colours through :func:`point_colors` (``colormap.lut`` + ``lut_index``).
5. Eye-dome lighting when ``render.edl.enabled`` (:func:`pointflow.render.rules.edl_shade`
   over the winners' log2 view depth, float64).

Same input → same image, bit for bit (no threads, no float reassociation).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np

from ..config import RenderConfig
from . import colormap
from .base import FrameInput, FrameStats, Renderer
from .camera import Camera
from .rules import apply_shade, edl_offsets, edl_shade

__all__ = ["CpuRenderer", "Selection", "pcg_hash", "select_points", "point_colors", "point_sizes_px",
           "rgba_u8", "keep_probability", "MAX_POINT_PX", "seed_hash", "budget_seed", "uniform01",
           "importance_range_for_budget"]

#: World-size points are clamped to [1, MAX_POINT_PX] pixels (a point at the near plane
#: would otherwise cover an unbounded area; sub-pixel points would vanish).
MAX_POINT_PX = 4096.0
_FRAGMENT_BATCH = 1 << 22  # fragments per splat batch (bounds memory: ~6 arrays of 8 B each)
_U32 = np.uint32
_OFFSET_LOOP_MAX = 1024  # constant sizes up to ~30 px splat one footprint offset at a time


# --------------------------------------------------------------------------- hashing
def _pcg(v: np.ndarray) -> np.ndarray:
    # PCG-RXS-M-XS 32 (Jarzynski & Olano 2020, "Hash Functions for GPU Rendering").
    state = v * _U32(747796405) + _U32(2891336453)
    word = ((state >> ((state >> _U32(28)) + _U32(4))) ^ state) * _U32(277803737)
    return (word >> _U32(22)) ^ word


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


# --------------------------------------------------------------------------- selection
@dataclass
class Selection:
    """Survivors of the per-frame filters, in ascending logical order."""

    logical: np.ndarray          # int64 logical indices (0 = oldest)
    slots: np.ndarray            # int64 ring slots
    counts: dict[str, int] = field(default_factory=dict)  # removed per filter + occupied/drawn

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


def select_points(frame: FrameInput, camera: Camera, cfg: RenderConfig, width: int, height: int) -> Selection:
    """Apply, in order: finite positions, time window (``now - t <= window``, off when 0),
    LOD stride (``logical % stride == 0``), importance sampling (``uniform01(slot,
    seed_hash(seed)) <= p`` in float32, p from :func:`keep_probability` over the
    ``importance`` range), frustum (all six planes ``>= 0``, float64, a point on a plane is
    kept), and the budget, only when survivors n > budget b: keep iff ``uniform01(slot,
    budget_seed(seed)) < max(b - 3 sqrt(b), b / 2) / n`` (float32), then at most the first
    b in logical order.
    These are the wgpu tier's rules (``wgpu_tier/reference.py``) except that the GPU's
    final truncation picks an arbitrary b."""
    cap, size = check_frame(frame)
    counts = {"occupied": size, "nonfinite": 0, "time_window": 0, "lod": 0, "sampled": 0, "frustum": 0,
              "budget": 0}
    logical = np.arange(size, dtype=np.int64)
    slots = (int(frame.head) + logical) % cap
    pos = frame.positions[slots]
    keep = np.isfinite(pos).all(axis=1)
    counts["nonfinite"] = int(size - np.count_nonzero(keep))
    if cfg.time_window_ms > 0:
        t = np.asarray(frame.t_ingest_ms[slots], np.float64)
        tw = (float(frame.now_ms) - t) <= float(cfg.time_window_ms)
        counts["time_window"] = int(np.count_nonzero(keep & ~tw))
        keep &= tw
    if cfg.lod_stride > 1:
        lod = (logical % int(cfg.lod_stride)) == 0
        counts["lod"] = int(np.count_nonzero(keep & ~lod))
        keep &= lod
    if cfg.importance_sampling:
        lo, hi = frame.channel_ranges.get("importance") or _finite_range(frame.importance[slots])
        idx = np.flatnonzero(keep)
        p = keep_probability(frame.importance[slots[idx]], lo, hi)
        u = uniform01(slots[idx], seed_hash(frame.frame_seed))
        drop = idx[~(u <= p)]
        counts["sampled"] = int(drop.size)
        keep[drop] = False
    idx = np.flatnonzero(keep)
    if idx.size:
        planes = camera.frustum_planes(width, height, frame.origin)
        d = pos[idx].astype(np.float64) @ planes[:, :3].T + planes[:, 3]
        inside = (d >= 0.0).all(axis=1)
        counts["frustum"] = int(idx.size - np.count_nonzero(inside))
        idx = idx[inside]
    if frame.budget is not None and idx.size > max(int(frame.budget), 0):
        b = max(int(frame.budget), 0)
        fb = np.float32(b)  # aim three standard deviations under b: the set depends only on the hash
        frac = np.float32(max(fb - np.float32(3.0) * np.sqrt(fb), np.float32(0.5) * fb)) / np.float32(idx.size)
        before = idx.size
        idx = idx[uniform01(slots[idx], budget_seed(frame.frame_seed)) < frac][:b]
        counts["budget"] = int(before - idx.size)
    counts["drawn"] = int(idx.size)
    return Selection(logical=logical[idx], slots=slots[idx], counts=counts)


# --------------------------------------------------------------------------- colour & size
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
        occ = occ[np.isfinite(frame.positions[occ]).all(axis=1)]
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


# --------------------------------------------------------------------------- the tier
class CpuRenderer(Renderer):
    """numpy tier: the float64 reference (deterministic, no device needed)."""

    tier = "cpu"

    def __init__(self, cfg: RenderConfig, capacity: int, channels: list[str]):
        super().__init__(cfg, capacity, channels)
        self._bg = rgba_u8(cfg.background)
        h, w = self.height, self.width
        self._image = np.empty((h, w, 4), np.uint8)
        self._image[:] = self._bg
        self._slot_at = np.full(h * w, -1, np.int64)      # ring slot drawn at each pixel
        self._last: dict[str, np.ndarray] = {}  # drawn points' attributes, for pick strategies
        self._edl = edl_offsets(cfg.edl.radius_px) if cfg.edl.enabled else None
        self.nonfinite_total = 0
        self.frames = 0

    # ---------------------------------------------------------------- render
    def render(self, frame: FrameInput, camera: Camera) -> FrameStats:
        t0 = time.perf_counter()
        W, H = self.width, self.height
        sel = select_points(frame, camera, self.cfg, W, H)
        t1 = time.perf_counter()
        vp = camera.view_proj(W, H, frame.origin)
        p = frame.positions[sel.slots].astype(np.float64)
        clip = p @ vp.T[:3] + vp[:, 3]
        w = clip[:, 3]
        px = (clip[:, 0] / w * 0.5 + 0.5) * W
        py = (0.5 - clip[:, 1] / w * 0.5) * H
        depth = clip[:, 2] / w
        sizes = point_sizes_px(self.cfg, camera, W, H, w)
        colors = point_colors(frame, self.cfg, sel.slots)
        order = np.lexsort((sel.logical, depth))  # rank: nearest first, ties → lower logical index
        t2 = time.perf_counter()
        winner = self._splat(px[order], py[order], sizes if np.isscalar(sizes) else sizes[order])
        t3 = time.perf_counter()
        hit = winner >= 0
        img = self._image.reshape(-1, 4)
        img[:] = self._bg
        img[hit] = colors[order][winner[hit]]
        self._slot_at[:] = -1
        self._slot_at[hit] = sel.slots[order][winner[hit]]
        if self._edl is not None:  # eye-dome lighting over the winners' log2 linear depth (= clip w)
            logz = np.zeros(W * H, np.float64)
            logz[hit] = np.log2(w[order][winner[hit]])
            shade = edl_shade(logz.reshape(H, W), hit.reshape(H, W), self._edl, self.cfg.edl.strength)
            self._image[:] = apply_shade(self._image, shade)
        self._last = drawn_attributes(frame, sel.slots) if self.cfg.pick_strategy != "nearest" else {}
        t4 = time.perf_counter()
        self.nonfinite_total += sel.counts["nonfinite"]
        self.frames += 1
        ms = lambda a, b: (b - a) * 1e3
        return FrameStats(
            drawn=sel.n,
            timings_ms={"select": ms(t0, t1), "project": ms(t1, t2), "splat": ms(t2, t3),
                        "resolve": ms(t3, t4), "total": ms(t0, t4)},
            extra={**{f"removed_{k}": v for k, v in sel.counts.items() if k not in ("occupied", "drawn")},
                   "nonfinite_total": self.nonfinite_total},
        )

    def _splat(self, px: np.ndarray, py: np.ndarray, size) -> np.ndarray:
        """Rank of the winning point per pixel (-1 = background); points come ranked."""
        W, H = self.width, self.height
        n = px.size
        best = np.full(W * H, np.iinfo(np.int64).max, np.int64)
        if n:
            half = np.asarray(size, np.float64) * 0.5
            round_ = self.cfg.point_shape == "round"
            # square: centres c in [p - s/2, p + s/2); round: |c - p| <= s/2 (then masked)
            x0 = np.ceil(px - half - 0.5)
            y0 = np.ceil(py - half - 0.5)
            if round_:
                x1 = np.floor(px + half - 0.5) + 1
                y1 = np.floor(py + half - 0.5) + 1
            else:
                x1 = np.ceil(px + half - 0.5)
                y1 = np.ceil(py + half - 0.5)
            x0 = np.clip(x0, 0, W).astype(np.int64)
            x1 = np.clip(x1, 0, W).astype(np.int64)
            y0 = np.clip(y0, 0, H).astype(np.int64)
            y1 = np.clip(y1, 0, H).astype(np.int64)
            bw = np.maximum(x1 - x0, 0)
            bh = np.maximum(y1 - y0, 0)
            if half.ndim == 0 and (2 * int(np.ceil(float(half))) + 2) ** 2 <= _OFFSET_LOOP_MAX:
                self._splat_offsets(best, px, py, float(half), x0, x1, y0, y1, round_)
                best[best == np.iinfo(np.int64).max] = -1
                return best
            cnt = bw * bh
            ends = np.cumsum(cnt)
            start = 0
            while start < n:
                # the largest batch of points whose fragments fit the batch size (>= 1 point)
                base = ends[start - 1] if start else 0
                stop = max(int(np.searchsorted(ends, base + _FRAGMENT_BATCH, side="right")), start + 1)
                stop = min(stop, n)
                c = cnt[start:stop]
                total = int(c.sum())
                if total:
                    pid = np.repeat(np.arange(start, stop, dtype=np.int64), c)
                    first = np.cumsum(c) - c
                    off = np.arange(total, dtype=np.int64) - np.repeat(first, c)
                    bwp = bw[pid]
                    X = x0[pid] + off % bwp
                    Y = y0[pid] + off // bwp
                    if round_:
                        hp = half if half.ndim == 0 else half[pid]
                        dx = X + 0.5 - px[pid]
                        dy = Y + 0.5 - py[pid]
                        m = dx * dx + dy * dy <= hp * hp
                        X, Y, pid = X[m], Y[m], pid[m]
                    np.minimum.at(best, Y * W + X, pid)
                start = stop
        best[best == np.iinfo(np.int64).max] = -1
        return best

    def _splat_offsets(self, best, px, py, half: float, x0, x1, y0, y1, round_: bool) -> None:
        """Constant point size: one vectorised pass over all points per footprint offset
        (a loop over at most _OFFSET_LOOP_MAX offsets, never over points)."""
        W = self.width
        rank = np.arange(px.size, dtype=np.int64)
        k = int(np.ceil(half)) + 1  # the clipped box spans at most 2k pixels per axis
        for dy in range(2 * k):
            Y = y0 + dy
            my = Y < y1
            if not my.any():
                break
            for dx in range(2 * k):
                X = x0 + dx
                m = my & (X < x1)
                if not m.any():
                    break
                if round_:
                    ex = X + 0.5 - px
                    ey = Y + 0.5 - py
                    m &= ex * ex + ey * ey <= half * half
                np.minimum.at(best, (Y * W + X)[m], rank[m])

    # ---------------------------------------------------------------- outputs
    def read_image(self) -> np.ndarray:
        return self._image.copy()

    def pick(self, x: float, y: float, pixel_ratio: float = 1.0) -> Optional[int]:
        win = pick_window(self.width, self.height, x, y, pixel_ratio, self.cfg.pick_radius)
        if win is None:
            return None
        X, Y, xa, xb, ya, yb = win
        block = self._slot_at.reshape(self.height, self.width)[ya:yb, xa:xb]
        block = in_pick_circle(block, xa, ya, x, y, pixel_ratio, self.cfg.pick_radius)
        return resolve_pick(block, X - xa, Y - ya, self.cfg.pick_strategy, self._last)

    def info(self) -> dict[str, Any]:
        return {"tier": self.tier, "size": [self.width, self.height], "numpy": np.__version__,
                "deterministic": True}
