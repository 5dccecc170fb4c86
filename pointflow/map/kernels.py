"""Compiled loops of the index build (numba): Morton codes and the level each point lives at.

A point's code interleaves 21 bits of x, y and z (its cell at depth 21 of the root cube);
the node of depth d holding it is ``code >> 3 * (21 - d)``, so one sort by code lays every
node of every depth out as a contiguous run."""
from __future__ import annotations

import numba
import numpy as np

DMAX = 21  # bits per axis in a code; the deepest possible node


@numba.njit(cache=True, nogil=True)
def _spread(v):
    v = v & np.uint64(0x1FFFFF)
    v = (v | (v << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
    v = (v | (v << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
    v = (v | (v << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
    v = (v | (v << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
    v = (v | (v << np.uint64(2))) & np.uint64(0x1249249249249249)
    return v


@numba.njit(cache=True, nogil=True, inline="always")
def _axis_bits(v, lo, scale, top, a):
    """Axis ``a``'s bits of a Morton code: the cell of ``v`` along it (clamped to the cube)."""
    q = int((v - lo) * scale) if v > lo else 0
    if q > top:
        q = top
    return _spread(np.uint64(q)) << np.uint64(2 - a)


@numba.njit(cache=True, nogil=True)
def morton_codes(pos, lo, side):
    """Codes of (n, 3) float64 positions in the cube [lo, lo + side); outside points clamp."""
    n = pos.shape[0]
    out = np.empty(n, np.uint64)
    scale = float(1 << DMAX) / side
    top = (1 << DMAX) - 1
    for i in range(n):
        c = np.uint64(0)
        for a in range(3):
            c |= _axis_bits(pos[i, a], lo[a], scale, top, a)
        out[i] = c
    return out


@numba.njit(cache=True, nogil=True)
def _compact(v):
    v = v & np.uint64(0x1249249249249249)
    v = (v | (v >> np.uint64(2))) & np.uint64(0x10C30C30C30C30C3)
    v = (v | (v >> np.uint64(4))) & np.uint64(0x100F00F00F00F00F)
    v = (v | (v >> np.uint64(8))) & np.uint64(0x1F0000FF0000FF)
    v = (v | (v >> np.uint64(16))) & np.uint64(0x1F00000000FFFF)
    v = (v | (v >> np.uint64(32))) & np.uint64(0x1FFFFF)
    return v


@numba.njit(cache=True, nogil=True)
def decode_prefixes(prefix):
    """(n,) node prefixes (code >> 3 * (21 - d)) -> (n, 3) int64 x, y, z at their depth."""
    n = prefix.shape[0]
    out = np.empty((n, 3), np.int64)
    for i in range(n):
        for a in range(3):
            out[i, a] = np.int64(_compact(prefix[i] >> np.uint64(2 - a)))
    return out


@numba.njit(cache=True, nogil=True)
def assign_levels(codes, l_start, l_stop, leaf_max, grid_bits, out):
    """Give each point (``codes`` sorted) the depth of the node that holds it.

    At depth l, a node with at most ``leaf_max`` points still unplaced is a leaf: it takes them
    all. Otherwise it takes one unplaced point per occupied cell of its own grid (2^grid_bits
    cells a side, i.e. the cells of depth l + grid_bits): a spread-out subset, finer at each
    depth. Points still unplaced after depth ``l_stop - 1`` get ``l_stop``. ``leaf_max < 0``:
    no leaves (the top of a tree whose deeper nodes are built elsewhere)."""
    n = codes.shape[0]
    left = 0
    for k in range(n):
        if out[k] < 0:
            left += 1
    for lvl in range(l_start, l_stop):
        if left == 0:
            break
        sh_node = np.uint64(3 * (DMAX - lvl))
        cb = DMAX - lvl - grid_bits
        sh_cell = np.uint64(3 * cb) if cb > 0 else np.uint64(0)
        i = 0
        while i < n:
            node = codes[i] >> sh_node
            j = i
            cnt = 0
            while j < n and (codes[j] >> sh_node) == node:
                if out[j] < 0:
                    cnt += 1
                j += 1
            if cnt > 0:
                if (leaf_max >= 0 and cnt <= leaf_max) or lvl == DMAX:
                    for k in range(i, j):
                        if out[k] < 0:
                            out[k] = lvl
                    left -= cnt
                else:
                    have = False
                    last = np.uint64(0)
                    for k in range(i, j):
                        if out[k] < 0:
                            c = codes[k] >> sh_cell
                            if not have or c != last:
                                out[k] = lvl
                                left -= 1
                                last = c
                                have = True
            i = j
    if left:
        for k in range(n):
            if out[k] < 0:
                out[k] = l_stop
    return out


@numba.njit(cache=True, nogil=True)
def morton_codes_int(X, Y, Z, scales, offsets, lo, side):
    """Codes straight from LAS integer coordinates (X * scale + offset, as laspy scales them),
    without the (n, 3) float64 positions in between."""
    n = X.shape[0]
    out = np.empty(n, np.uint64)
    scale = float(1 << DMAX) / side
    top = (1 << DMAX) - 1
    for i in range(n):
        c = np.uint64(0)
        for a in range(3):
            raw = X[i] if a == 0 else (Y[i] if a == 1 else Z[i])
            c |= _axis_bits(raw * scales[a] + offsets[a], lo[a], scale, top, a)
        out[i] = c
    return out


@numba.njit(cache=True, nogil=True)
def bucket_order(keys, nbuckets):
    """A stable counting sort: the permutation that orders ``keys`` (ints in [0, nbuckets)) and
    the start of each bucket in it (``nbuckets + 1`` entries)."""
    n = keys.shape[0]
    starts = np.zeros(nbuckets + 1, np.int64)
    for i in range(n):
        starts[keys[i] + 1] += 1
    for b in range(nbuckets):
        starts[b + 1] += starts[b]
    pos = starts[:-1].copy()
    perm = np.empty(n, np.int64)
    for i in range(n):
        k = keys[i]
        perm[pos[k]] = i
        pos[k] += 1
    return perm, starts
