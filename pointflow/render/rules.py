"""The draw rules every render tier follows, written once (float64/numpy reference).

Tiers import these; no tier imports another tier. The GPU tiers implement the same rules in
their shaders and are tested against these functions.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["EDL_NEIGHBOURS", "EDL_SCALE", "edl_offsets", "edl_shade", "apply_shade"]


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
    d = np.where(covered, np.asarray(log_depth, np.float64), 0.0)
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
        both = covered[py, px] & covered[qy, qx]
        resp[py, px] += np.where(both, np.maximum(0.0, d[py, px] - d[qy, qx]), 0.0)
    resp /= EDL_NEIGHBOURS
    shade = np.exp(-EDL_SCALE * float(strength) * resp)
    shade[~covered] = 1.0
    return shade


def apply_shade(image: np.ndarray, shade: np.ndarray) -> np.ndarray:
    """(h, w, 4) uint8 with RGB multiplied by ``shade`` and rounded to nearest
    (``floor(c * shade + 0.5)``, as a unorm8 render target stores it); alpha unchanged.
    A shade of exactly 1 leaves the colour byte-identical."""
    out = image.copy()
    rgb = np.floor(image[..., :3].astype(np.float64) * shade[..., None] + 0.5)
    out[..., :3] = np.clip(rgb, 0, 255).astype(np.uint8)
    return out
