"""float64/numpy reference of the wgpu tier's per-point rules (tests and other tiers use it).

Every rule here is what ``shaders.CULL`` computes on the GPU, so another tier can select
exactly the same points:

* occupancy: slot ``s`` is occupied iff ``(s - head) % capacity < size``; its logical
  index is ``(s - head) % capacity`` (0 = oldest).
* finite: a point with a NaN/Inf coordinate is never drawn.
* time window (``window_ms > 0``): keep iff ``now_ms - t_ingest_ms <= window_ms``.
* frustum: keep iff ``a*x + b*y + c*z + d >= 0`` for all 6 planes (origin-relative).
* LOD stride: keep iff ``logical % lod_stride == 0``.
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

_M32 = np.uint64(0xFFFFFFFF)


def pcg_hash(v) -> np.ndarray:
    """PCG RXS-M-XS 32-bit hash (Jarzynski & Olano 2020), vectorised, uint32 in/out."""
    x = np.asarray(v).astype(np.uint64) & _M32
    state = (x * np.uint64(747796405) + np.uint64(2891336453)) & _M32
    word = (((state >> ((state >> np.uint64(28)) + np.uint64(4))) ^ state) * np.uint64(277803737)) & _M32
    return ((word >> np.uint64(22)) ^ word).astype(np.uint32)


def seed_hash(frame_seed: int) -> int:
    """Per-frame seed for importance sampling."""
    return int(pcg_hash(np.uint64(int(frame_seed) & 0xFFFFFFFF)))


def budget_seed(frame_seed: int) -> int:
    """Per-frame seed for budget thinning (independent of the importance draw)."""
    return int(pcg_hash(np.uint64(seed_hash(frame_seed) ^ 0x9E3779B9)))


def uniform01(slots: np.ndarray, seed: int) -> np.ndarray:
    """The GPU's uniform draw in [0, 1): top 24 bits of the hash, exact in float32."""
    h = pcg_hash(np.asarray(slots, np.uint64) ^ np.uint64(seed))
    return (h >> np.uint32(8)).astype(np.float32) * np.float32(2.0 ** -24)


def normalised_importance(imp: np.ndarray, rng: Optional[tuple[float, float]]) -> np.ndarray:
    imp = np.asarray(imp, np.float32)
    if rng is None or not float(rng[1]) > float(rng[0]):
        return np.ones(imp.shape, np.float32)
    lo, hi = float(rng[0]), float(rng[1])
    n = (imp - np.float32(lo)) * np.float32(1.0 / (hi - lo))
    n = np.clip(n, 0.0, 1.0).astype(np.float32)
    n[~np.isfinite(n)] = 0.0
    return n


def keep_mask(positions: np.ndarray, head: int, size: int, capacity: int, planes: np.ndarray, *,
              t_ingest_ms: Optional[np.ndarray] = None, now_ms: float = 0.0, window_ms: float = 0.0,
              lod_stride: int = 1, importance: Optional[np.ndarray] = None,
              importance_range: Optional[tuple[float, float]] = None, frame_seed: int = 0) -> np.ndarray:
    """(capacity,) bool: points that survive the cull (before the budget), float64 maths."""
    cap = int(capacity)
    slots = np.arange(cap, dtype=np.int64)
    logical = (slots - int(head)) % max(cap, 1)
    keep = logical < int(size)
    p = np.asarray(positions, np.float64)
    keep &= np.isfinite(p).all(axis=1)
    if window_ms > 0 and t_ingest_ms is not None:
        with np.errstate(invalid="ignore"):
            keep &= (float(now_ms) - np.asarray(t_ingest_ms, np.float64)) <= float(window_ms)
    with np.errstate(invalid="ignore"):
        d = p @ np.asarray(planes, np.float64)[:, :3].T + np.asarray(planes, np.float64)[:, 3]
        keep &= (d >= 0).all(axis=1)
    if lod_stride > 1:
        keep &= (logical % int(lod_stride)) == 0
    if importance is not None:
        u = uniform01(slots, seed_hash(frame_seed))
        keep &= u <= normalised_importance(importance, importance_range)
    return keep


def budget_fraction(budget: int, survivors: int) -> float:
    """Keep probability of a survivor under the budget (float32, as on the GPU)."""
    if survivors <= budget:
        return 2.0
    b = np.float32(budget)
    return float(np.float32(max(b - np.float32(3.0) * np.sqrt(b), np.float32(0.5) * b)) / np.float32(survivors))


def plane_margin(positions: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """(N,) smallest relative distance |dist| / (|a x|+|b y|+|c z|+|d|) to any plane."""
    p = np.asarray(positions, np.float64)
    pl = np.asarray(planes, np.float64)
    d = np.abs(p @ pl[:, :3].T + pl[:, 3])
    scale = np.abs(p) @ np.abs(pl[:, :3]).T + np.abs(pl[:, 3])
    with np.errstate(invalid="ignore", divide="ignore"):
        return (d / np.maximum(scale, 1e-300)).min(axis=1)  # NaN for non-finite points
