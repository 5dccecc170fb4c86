"""Colormaps as 256-entry RGBA uint8 lookup tables shared by every tier.

A scalar v maps to index ``floor(clip((v - lo) / (hi - lo), 0, 1) * 255 + 0.5)``; when
``hi <= lo`` (degenerate range) every value maps to index 255. NaN maps to the single
``color`` of the render config (a channel the point's chunk did not carry).
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

NAMES = ("turbo", "viridis", "grayscale")


def _turbo(x: np.ndarray) -> np.ndarray:
    # Polynomial approximation of Google's Turbo (Mikhailov 2019).
    v4 = np.stack([np.ones_like(x), x, x * x, x * x * x], axis=-1)
    v2 = np.stack([v4[:, 2] * v4[:, 2], v4[:, 3] * v4[:, 2]], axis=-1)
    r = v4 @ [0.13572138, 4.61539260, -42.66032258, 132.13108234] + v2 @ [-152.94239396, 59.28637943]
    g = v4 @ [0.09140261, 2.19418839, 4.84296658, -14.18503333] + v2 @ [4.27729857, 2.82956604]
    b = v4 @ [0.10667330, 12.64194608, -60.58204836, 110.36276771] + v2 @ [-89.90310912, 27.34824973]
    return np.stack([r, g, b], axis=-1)


def _viridis(t: np.ndarray) -> np.ndarray:
    c = np.array([
        [0.2777273272234177, 0.005407344544966578, 0.3340998053353061],
        [0.1050930431085774, 1.404613529898575, 1.384590162594685],
        [-0.3308618287255563, 0.214847559468213, 0.09509516302823659],
        [-4.634230498983486, -5.799100973351585, -19.33244095627987],
        [6.228269936347081, 14.17993336680509, 56.69055260068105],
        [4.776384997670288, -13.74514537774601, -65.35303263337234],
        [-5.435455855934631, 4.645852612178535, 26.3124352495832],
    ])
    out = np.zeros((t.shape[0], 3))
    for k in range(6, -1, -1):  # Horner, 7 coefficients (not a loop over points)
        out = out * t[:, None] + c[k]
    return out


@lru_cache(maxsize=None)
def lut(name: str) -> np.ndarray:
    """(256, 4) uint8 RGBA table."""
    t = np.linspace(0.0, 1.0, 256)
    if name == "turbo":
        rgb = _turbo(t)
    elif name == "viridis":
        rgb = _viridis(t)
    elif name == "grayscale":
        rgb = np.stack([t, t, t], axis=-1)
    else:
        raise ValueError(f"colormap must be one of {', '.join(NAMES)}; got {name!r}")
    out = np.empty((256, 4), np.uint8)
    out[:, :3] = np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8)
    out[:, 3] = 255
    out.flags.writeable = False
    return out


def lut_index(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Indices into a LUT (int32), the exact rule every tier follows. NaN -> -1."""
    v = np.asarray(values, dtype=np.float32)
    if not hi > lo:
        idx = np.full(v.shape, 255, np.int32)
    else:
        # float32 arithmetic, as on the GPU
        with np.errstate(invalid="ignore"):  # NaN is handled below
            t = (v - np.float32(lo)) * np.float32(1.0 / (hi - lo))
            idx = np.floor(np.nan_to_num(np.clip(t, 0.0, 1.0)) * np.float32(255.0) + np.float32(0.5)).astype(np.int32)
    idx[~np.isfinite(v)] = -1
    return idx
