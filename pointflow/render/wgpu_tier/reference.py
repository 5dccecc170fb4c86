"""The wgpu tier's per-point rules in per-slot form (float64/numpy), for its tests.

The rules themselves (hash, draws, keep probability, budget fraction) are
:mod:`pointflow.render.rules`, shared by every tier; here they are applied slot by slot, the
way ``shaders.CULL`` computes them on the GPU:

* occupancy: slot ``s`` is occupied iff ``(s - head) % capacity < size``; its logical
  index is ``(s - head) % capacity`` (0 = oldest).
* finite: a point with a NaN/Inf coordinate is never drawn.
* time window (``window_ms > 0``): keep iff ``now_ms - t_ingest_ms <= window_ms``.
* frustum: keep iff ``a*x + b*y + c*z + d >= 0`` for all 6 planes (origin-relative).
* LOD stride: keep iff ``logical % lod_stride == 0``.
* footprint LOD (``render.lod_fill``): keep iff ``slot & masks[slot >> 14] == 0``, the masks
  per batch of the whole ring from :func:`pointflow.render.batches.lod_masks`.
* importance sampling: ``u = (pcg_hash(slot ^ seed_hash(frame_seed)) >> 8) * 2**-24`` and
  keep iff ``u <= clip((imp - lo) / (hi - lo), 0, 1)`` (1.0 when ``hi <= lo``; a NaN
  importance counts as 0). The *slot* (not the logical index) is hashed, so with a fixed
  seed a point's fate does not change as the ring scrolls.
* budget B (applied last, only when survivors S > B): keep a survivor iff
  ``(pcg_hash(slot ^ budget_seed) >> 8) * 2**-24 < max(B - 3*sqrt(B), B/2) / S`` (aiming
  three standard deviations under B, so the hard cap rarely bites); if that still leaves
  more than B, the first B in logical order are drawn (the oldest).

Survivors are compacted in logical order (per-workgroup counts + a prefix sum, no atomic
ordering), so equal-depth ties go to the lower logical index, as in every tier.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from ...arrays import finite_rows
from ..batches import BATCH_SHIFT
from ..rules import budget_fraction, budget_seed, keep_probability, pcg, seed_hash, uniform01

#: The WGSL ``pcg(v)`` (tests and callers of this module know it by this name).
pcg_hash = pcg

__all__ = ["pcg_hash", "seed_hash", "budget_seed", "uniform01", "budget_fraction", "normalised_importance",
           "keep_mask", "plane_margin"]


def normalised_importance(imp: np.ndarray, rng: Optional[tuple[float, float]]) -> np.ndarray:
    """rules.keep_probability over ``rng`` (1.0 everywhere without a range)."""
    if rng is None:
        return np.ones(np.shape(imp), np.float32)
    return keep_probability(imp, float(rng[0]), float(rng[1]))


def keep_mask(positions: np.ndarray, head: int, size: int, capacity: int, planes: np.ndarray, *,
              t_ingest_ms: Optional[np.ndarray] = None, now_ms: float = 0.0, window_ms: float = 0.0,
              lod_stride: int = 1, batch_lod: Optional[np.ndarray] = None, importance: Optional[np.ndarray] = None,
              importance_range: Optional[tuple[float, float]] = None, frame_seed: int = 0) -> np.ndarray:
    """(capacity,) bool: points that survive the cull (before the budget), float64 maths."""
    cap = int(capacity)
    slots = np.arange(cap, dtype=np.int64)
    logical = (slots - int(head)) % max(cap, 1)
    keep = logical < int(size)
    p = np.asarray(positions, np.float64)
    keep &= finite_rows(p)
    if window_ms > 0 and t_ingest_ms is not None:
        with np.errstate(invalid="ignore"):
            keep &= (float(now_ms) - np.asarray(t_ingest_ms, np.float64)) <= float(window_ms)
    with np.errstate(invalid="ignore"):
        d = p @ np.asarray(planes, np.float64)[:, :3].T + np.asarray(planes, np.float64)[:, 3]
        keep &= (d >= 0).all(axis=1)
    if lod_stride > 1:
        keep &= (logical % int(lod_stride)) == 0
    if batch_lod is not None:
        keep &= (slots & np.asarray(batch_lod, np.int64)[slots >> BATCH_SHIFT]) == 0
    if importance is not None:
        u = uniform01(slots, seed_hash(frame_seed))
        keep &= u <= normalised_importance(importance, importance_range)
    return keep


def plane_margin(positions: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """(N,) smallest relative distance |dist| / (|a x|+|b y|+|c z|+|d|) to any plane."""
    p = np.asarray(positions, np.float64)
    pl = np.asarray(planes, np.float64)
    d = np.abs(p @ pl[:, :3].T + pl[:, 3])
    scale = np.abs(p) @ np.abs(pl[:, :3]).T + np.abs(pl[:, 3])
    with np.errstate(invalid="ignore", divide="ignore"):
        return (d / np.maximum(scale, 1e-300)).min(axis=1)  # NaN for non-finite points
