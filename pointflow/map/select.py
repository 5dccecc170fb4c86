"""Which nodes a view needs: by projected size, within a point budget, coarse first.

Potree's rule: from the roots, visit nodes in order of their size on screen (biggest first);
take a node while the points taken stay within the budget, and queue its children; a node
outside the view frustum is dropped with its subtree. A parent is always taken before its
children, so the list is coarse first and any prefix of it is a usable picture. A node's box
is tested against the frustum by the same plane test that culls the ring's batches in every
render tier (:func:`pointflow.render.batches.boxes_outside`): one idea for boxes of points."""
from __future__ import annotations

import heapq
from typing import Iterable, Optional

import numpy as np

from ..render.batches import boxes_outside
from ..render.camera import planes_of


def select_nodes(source, view_proj, viewport, eye, budget: int, loaded: Optional[Iterable] = None, *,
                 origin=None, min_spacing_px: float = 0.0) -> list:
    """Keys of the nodes to draw, coarse first, with at most ``budget`` points in all.

    ``view_proj`` (4x4, proj @ view) maps world coordinates (float64) to clip space; with
    ``origin`` it maps coordinates relative to that origin (and ``eye`` is relative too).
    ``viewport`` is (width, height) in pixels. A node's priority is its projected size in
    pixels (its half-diagonal over its distance, times the focal length in pixels); nodes whose
    points would be closer than ``min_spacing_px`` on screen are not refined. Among nodes of
    equal priority those in ``loaded`` come first (no reload for a tie)."""
    vp = np.asarray(view_proj, np.float64).reshape(4, 4)
    h_px = float(viewport[1])
    focal = 0.5 * h_px * float(np.linalg.norm(vp[1, :3]))  # P[1][1] * h / 2 for proj @ rigid view
    eye = np.asarray(eye, np.float64)
    shift = np.zeros(3) if origin is None else np.asarray(origin, np.float64)
    loaded = set(loaded or ())
    planes = planes_of(vp)  # the frustum of the coordinates vp maps (origin-relative with origin)
    heap: list = []
    tie = 0

    def push(key) -> None:
        nonlocal tie
        n = source.node(key)
        lo, hi = n.lo - shift, n.hi - shift
        if boxes_outside(lo[None], hi[None], planes)[0]:
            return  # wholly outside one plane: no point of it or its subtree is drawn
        centre = (lo + hi) / 2
        radius = float(np.linalg.norm(hi - lo)) / 2
        wc = float(centre @ vp[3, :3] + vp[3, 3])
        dist = max(float(np.linalg.norm(centre - eye)) if vp[3, :3].any() else 1.0, 1e-9) if wc > 0 else 0.0
        size = float("inf") if dist <= radius or wc <= 0 else radius * focal / dist
        spacing_px = float("inf") if size == float("inf") else n.spacing * focal / max(dist, 1e-9)
        tie += 1
        heapq.heappush(heap, (-size, key not in loaded, tie, key, n.count, spacing_px))

    for k in source.root_keys():
        push(k)
    out, total = [], 0
    while heap:
        _, _, _, key, count, spacing_px = heapq.heappop(heap)
        if total + count > budget:
            break
        out.append(key)
        total += count
        if spacing_px >= min_spacing_px:
            for c in source.children(key):
                push(c)
    return out
