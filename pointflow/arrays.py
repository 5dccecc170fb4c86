"""Reductions over (n, 3) point arrays, done column by column.

numpy reduces a short last axis one row at a time, and an (n, 3) array along axis 0 with
a 3-element inner loop: for 1M float32 points ``np.isfinite(p).all(axis=1)`` took 15 ms
where three column tests joined by ``&`` took 0.8 ms, and ``p.min(axis=0)`` 26 ms against
1.2 ms (numpy 2.4, the 2-core machine). Paths that run per frame or per chunk over a
ring's or a file's points call these; the results are the same values.
"""
from __future__ import annotations

import numpy as np

__all__ = ["column_max", "column_min", "finite_rows", "rgb_u8"]


def finite_rows(p: np.ndarray) -> np.ndarray:
    """(n,) bool: rows of the (n, k) array ``p`` whose every value is finite."""
    p = np.asarray(p)
    if p.ndim != 2 or p.shape[1] == 0:
        return np.isfinite(p).all(axis=-1)
    out = np.isfinite(p[:, 0])
    for i in range(1, p.shape[1]):
        out &= np.isfinite(p[:, i])
    return out


def column_min(p: np.ndarray) -> np.ndarray:
    """``p.min(axis=0)`` of an (n, k) array with n >= 1 (NaN in a column gives NaN)."""
    p = np.asarray(p)
    return np.array([p[:, i].min() for i in range(p.shape[1])], dtype=p.dtype.newbyteorder("="))


def column_max(p: np.ndarray) -> np.ndarray:
    """``p.max(axis=0)`` of an (n, k) array with n >= 1 (NaN in a column gives NaN)."""
    p = np.asarray(p)
    return np.array([p[:, i].max() for i in range(p.shape[1])], dtype=p.dtype.newbyteorder("="))


def rgb_u8(arr: np.ndarray) -> np.ndarray:
    """Integer colour as the ring stores it (8 bits): 16-bit colour (LAS) scaled down, unless
    its values only use the 8-bit range (many LAS writers, the Autzen tile among them, store
    0..255 in the 16-bit fields; shifting those would draw them black)."""
    if arr.size and int(arr.max()) > 255:
        return (np.clip(arr, 0, 65535).astype(np.uint32) >> 8).astype(np.uint8)
    return np.clip(arr, 0, 255).astype(np.uint8)
