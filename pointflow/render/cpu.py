"""The numpy render tier: the deterministic float64 reference every other tier is measured against.

Per frame (all vectorised numpy, no Python loops over points):

1. :func:`~pointflow.render.rules.select_points` — occupancy, finite positions, time window,
   LOD stride, importance sampling, frustum, budget (the shared rules in
   :mod:`pointflow.render.rules`, so the gl tier draws the same survivors).
2. Projection of the survivors in float64 with ``camera.view_proj(w, h, origin)``.
3. A z-buffered splat: each point covers the pixels of its footprint
   (:func:`~pointflow.render.rules.footprint_box`); nearer depth wins, ties go to the lower logical index.
   Points are ranked once by (depth, logical index); every pixel keeps its lowest rank.
4. Colours through :func:`~pointflow.render.rules.point_colors` (``colormap.lut`` + ``lut_index``).
5. Eye-dome lighting when ``render.edl.enabled`` (:func:`pointflow.render.rules.edl_shade`
   over the winners' log2 view depth, float64).

Same input → same image, bit for bit (no threads, no float reassociation).
"""
from __future__ import annotations

import time
from typing import Any, Optional

import numpy as np

from .config import RenderConfig
from .base import FrameInput, FrameStats, Renderer
from .batches import BatchBounds, culling_enabled
from .camera import Camera
from .rules import (apply_shade, drawn_attributes, edl_offsets, edl_shade, footprint_box, in_pick_circle,
                    in_round_footprint, pick_window, point_colors, point_sizes_px, resolve_pick, rgba_u8,
                    select_points)

__all__ = ["CpuRenderer"]

_FRAGMENT_BATCH = 1 << 22  # fragments per splat batch (bounds memory: ~6 arrays of 8 B each)
_OFFSET_LOOP_MAX = 1024  # constant sizes up to ~30 px splat one footprint offset at a time


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
        self._bounds = BatchBounds() if culling_enabled() else None  # whole batches culled

    def resize(self, width: int, height: int) -> bool:
        """A target per size (image and slot map), kept for switching back."""
        size = (int(width), int(height))
        if size == (self.width, self.height):
            return True
        targets = self.__dict__.setdefault("_targets", {})
        targets[(self.width, self.height)] = (self._image, self._slot_at, self._last)
        if size in targets:
            self._image, self._slot_at, self._last = targets[size]
        else:
            self._image = np.empty((size[1], size[0], 4), np.uint8)
            self._image[:] = self._bg
            self._slot_at, self._last = np.full(size[0] * size[1], -1, np.int64), {}
        self.width, self.height = size
        return True

    def restyle(self, cfg: RenderConfig) -> bool:
        """Every style field is read per frame except EDL's offsets and the background."""
        self.cfg = cfg
        self._bg = rgba_u8(cfg.background)
        self._edl = edl_offsets(cfg.edl.radius_px) if cfg.edl.enabled else None
        return True

    # ---------------------------------------------------------------- render
    def render(self, frame: FrameInput, camera: Camera) -> FrameStats:
        t0 = time.perf_counter()
        W, H = self.width, self.height
        if self._bounds is not None:
            self._bounds.note(frame)
        sel = select_points(frame, camera, self.cfg, W, H, self._bounds)
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
        t_edl = time.perf_counter()
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
                        "resolve": ms(t3, t4), "total": ms(t0, t4),
                        **({"edl": ms(t_edl, t4)} if self._edl is not None else {})},
            extra={**{f"removed_{k}": v for k, v in sel.counts.items() if k not in ("occupied", "drawn")},
                   "nonfinite_total": self.nonfinite_total, "culled_points": sel.culled},
        )

    def _splat(self, px: np.ndarray, py: np.ndarray, size) -> np.ndarray:
        """Rank of the winning point per pixel (-1 = background); points come ranked."""
        W, H = self.width, self.height
        n = px.size
        best = np.full(W * H, np.iinfo(np.int64).max, np.int64)
        if n:
            half = np.asarray(size, np.float64) * 0.5
            round_ = self.cfg.point_shape == "round"
            x0, x1, y0, y1 = footprint_box(px, py, half, round_, W, H)  # round: then masked per pixel
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
                        m = in_round_footprint(X, Y, px[pid], py[pid], half if half.ndim == 0 else half[pid])
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
                    m &= in_round_footprint(X, Y, px, py, half)
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
