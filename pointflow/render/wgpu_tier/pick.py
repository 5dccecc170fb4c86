"""Picking in the wgpu tier: the block of texels under the cursor, and the choice among them."""
from __future__ import annotations

import math
from typing import Optional

import numpy as np


def pick_block(px: float, py: float, r: float, width: int, height: int) -> Optional[tuple[int, int, int, int]]:
    """(x0, y0, w, h) of the (2r+1)^2 texel block around physical pixel (px, py), clipped to
    the target; None when it lies outside."""
    ri = int(math.ceil(r))
    x0, x1 = max(int(math.floor(px)) - ri, 0), min(int(math.floor(px)) + ri + 1, width)
    y0, y1 = max(int(math.floor(py)) - ri, 0), min(int(math.floor(py)) + ri + 1, height)
    if x1 <= x0 or y1 <= y0:
        return None
    return x0, y0, x1 - x0, y1 - y0


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
