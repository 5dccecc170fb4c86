"""Compiled (numba) loops of the cpu tier's ``compute`` raster method (:mod:`.cpu_compute`).

The same key and rules as the wgpu compute method: every per-point test of
:mod:`pointflow.render.rules` fused with the projection and a write of the point's key
``bits(float32 w) << 32 | logical`` into every pixel of its footprint, the smallest key
winning (nearer linear depth, then the lower logical index). Parallel over the cores, two
ways: :func:`_raster` (chunks of logical indices, a key buffer per thread, the per-pixel
resolve takes the minimum over the buffers) and the binned pair :func:`_bin` + :func:`_bands`
(records sorted by screen band per chunk, then each band keyed and resolved by one thread).
Keys are unique, so the image does not depend on the thread count or the way. Projection and the
frustum test run in float64 like the numpy reference; colours follow ``colormap.lut_index``
in float32.

:func:`load` imports numba and makes the dispatchers (each loop compiles, or loads from the
disk cache, on its first call); it returns None when numba is missing or
``POINTFLOW_NO_NUMBA=1``. :func:`cache_state` says whether the first calls would compile:
the render stage then draws with another tier while :mod:`pointflow.jitcache` compiles
them in a process of its own (``pointflow warm`` does it ahead).
"""
from __future__ import annotations

import logging
import os
import threading
import warnings
from typing import Any, Optional

import numpy as np

from .batches import BATCH_SHIFT, LOD_CPU_COUNTED

log = logging.getLogger("pointflow.render.cpu_kernels")

#: an empty pixel (every real key is smaller: bits(w) of a finite w < 0x7f800000)
EMPTY = np.uint64(0xFFFFFFFFFFFFFFFF)
_M32 = np.uint64(0xFFFFFFFF)
_C1 = np.uint64(747796405)
_C2 = np.uint64(2891336453)
_C3 = np.uint64(277803737)
_U4 = np.uint64(4)
_U8 = np.uint64(8)
_U22 = np.uint64(22)
_U28 = np.uint64(28)
_U32 = np.uint64(32)
_HI32 = np.uint64(0xFFFFFFFF00000000)
_INV24 = np.float32(2.0 ** -24)
_F0 = np.float32(0.0)
_F1 = np.float32(1.0)
_F255 = np.float32(255.0)
_FH = np.float32(0.5)

# colour modes (the resolve pass)
C_SINGLE, C_RGB, C_SCALAR, C_Z, C_TIME = 0, 1, 2, 3, 4
# per-chunk counters written by the passes
ST_OCC, ST_BAD, ST_KEEP, ST_DRAWN = 0, 1, 2, 3
N_ST = 4

ENV_NO_NUMBA = "POINTFLOW_NO_NUMBA"


# --------------------------------------------------------------------------- the loops (plain Python, compiled by load())
def _pcg(v):
    # PCG RXS-M-XS 32 (rules.pcg) on a uint64 holding a uint32
    state = (v * _C1 + _C2) & _M32
    word = (((state >> ((state >> _U28) + _U4)) ^ state) * _C3) & _M32
    return ((word >> _U22) ^ word) & _M32


def _u01(slot, hseed):
    return np.float32(_pcg((np.uint64(slot) ^ hseed) & _M32) >> _U8) * _INV24


def _colour_value(cmode, slot, pos, tms, cval):
    if cmode == C_Z:
        return np.float64(pos[slot, 2])
    if cmode == C_TIME:
        return np.float64(tms[slot])
    return np.float64(cval[slot])


def _frustum(x, y, z, cx, cy, cz, w, planes, eps):
    """The six planes test of rules.select_points (float64, a point on a plane is kept).
    Clip space decides when it is clear by ``eps`` (far above float64 rounding of either
    form: the planes are the clip rows' sums, normalised); the planes decide otherwise."""
    a0 = w + cx
    a1 = w - cx
    a2 = w + cy
    a3 = w - cy
    a5 = w - cz
    if a0 > eps and a1 > eps and a2 > eps and a3 > eps and cz > eps and a5 > eps:
        return True
    if a0 < -eps or a1 < -eps or a2 < -eps or a3 < -eps or cz < -eps or a5 < -eps:
        return False
    for k in range(6):
        if planes[k, 0] * x + planes[k, 1] * y + planes[k, 2] * z + planes[k, 3] < 0.0:
            return False
    return True


def _test(logical, slot, tms, imp, has_window, now_ms, window_ms, lod, blod, has_imp, imp_degenerate, imp_lo,
          imp_scale, seed_h):
    """The tests after the frustum and before the budget (rules.select_points). ``blod``: the
    footprint LOD's mask per batch of slots (batches.lod_masks; empty when off)."""
    if has_window and not (now_ms - tms[slot]) <= window_ms:
        return False
    if lod > 1 and logical % lod != 0:
        return False
    if blod.shape[0] != 0 and (slot & blod[slot >> BATCH_SHIFT]) != 0:
        return False
    if has_imp:
        p = _F1
        if not imp_degenerate:
            p = (imp[slot] - imp_lo) * imp_scale  # float32, clipped as np.clip; NaN -> 0
            if p != p:
                p = _F0
            elif p < _F0:
                p = _F0
            elif p > _F1:
                p = _F1
        if not _u01(slot, seed_h) <= p:
            return False
    return True


def _f32_bits(typingctx, v):
    """The bits of a float32 as a uint32 (a register bit-cast; no scratch store)."""
    from llvmlite import ir
    from numba.core import types

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(32))
    return types.uint32(types.float32), codegen


def _store_box(kb, key, i, dx, dy, W):
    """``key`` min()-stored over the dx x dy box whose first pixel is ``i``: min() stores
    instead of a compare-and-branch (unpredictable), the 2x2, 2x1 and 1x1 boxes of 2 px and
    1 px points (2x1: a 2 px point cut by a band's edge) unrolled. An empty box stores nothing."""
    if dx == 2 and dy == 2:
        kb[i] = min(key, kb[i])
        kb[i + 1] = min(key, kb[i + 1])
        kb[i + W] = min(key, kb[i + W])
        kb[i + W + 1] = min(key, kb[i + W + 1])
    elif dx == 2 and dy == 1:
        kb[i] = min(key, kb[i])
        kb[i + 1] = min(key, kb[i + 1])
    elif dx == 1 and dy == 1:
        kb[i] = min(key, kb[i])
    else:
        for yy in range(dy):
            row = i + yy * W
            for xx in range(dx):
                kb[row + xx] = min(key, kb[row + xx])


#: the points split's key buffers in tiles of 2^TILE_XS x 2^TILE_YS pixels: each thread marks the
#: tiles it writes, so the clear and the resolve touch only those (a view whose points cover a
#: tenth of the screen clears and merges a tenth of the buffers: the full passes did not scale
#: with threads, T buffers of 8 bytes a pixel through memory)
TILE_XS = 5
TILE_YS = 4


def _tile_grid(W, H):
    """(columns, rows) of tiles over a W x H target."""
    return (W + (1 << TILE_XS) - 1) >> TILE_XS, (H + (1 << TILE_YS) - 1) >> TILE_YS


tile_grid = _tile_grid  # the Python function, for callers outside the loops (load() compiles _tile_grid)


def _tile_on(tm, ty, tx, TW):
    """Whether a buffer whose marks are ``tm`` may hold keys in tile (ty, tx): its own mark or
    the mark of the tile left, above or above-left of it (the hot loop marks a 2x2 box by the
    tile of its first pixel only; it reaches one tile right and down at most)."""
    i = ty * TW + tx
    if tm[i] != 0:
        return True
    if tx > 0 and tm[i - 1] != 0:
        return True
    if ty > 0:
        if tm[i - TW] != 0:
            return True
        if tx > 0 and tm[i - TW - 1] != 0:
            return True
    return False


def _mark_box(tm, x0, y0, x1, y1, TW):
    """Mark the tiles of the (non-empty) box [x0, x1) x [y0, y1): the tile of its first pixel
    when the box is no larger than a tile (it reaches one tile right and down at most:
    :func:`_tile_on`), else every tile it covers."""
    if x1 - x0 <= (1 << TILE_XS) and y1 - y0 <= (1 << TILE_YS):
        tm[(y0 >> TILE_YS) * TW + (x0 >> TILE_XS)] = 1
        return
    for ty in range(y0 >> TILE_YS, ((y1 - 1) >> TILE_YS) + 1):
        for tx in range(x0 >> TILE_XS, ((x1 - 1) >> TILE_XS) + 1):
            tm[ty * TW + tx] = 1


def _splat(kb, tm, TW, logical, cx, cy, w, W, H, half_px, world, size_scale, round_, ylo, yhi):
    """Write the point's key into every pixel of its footprint (rules.footprint_box) within
    rows [ylo, yhi) (a thread's band of the screen) and mark its tiles in ``tm``; (cx, cy, w)
    its clip coordinates."""
    px = (cx / w * 0.5 + 0.5) * W
    py = (0.5 - cy / w * 0.5) * H
    half = half_px
    if world:
        s = size_scale / w
        if s < 1.0:
            s = 1.0
        if s > 4096.0:
            s = 4096.0
        half = s * 0.5
    Wf = np.float64(W)
    Hf = np.float64(H)
    x0 = int(min(max(np.ceil(px - half - 0.5), 0.0), Wf))
    y0 = int(min(max(np.ceil(py - half - 0.5), 0.0), Hf))
    if round_:
        x1 = int(min(max(np.floor(px + half - 0.5) + 1.0, 0.0), Wf))
        y1 = int(min(max(np.floor(py + half - 0.5) + 1.0, 0.0), Hf))
    else:
        x1 = int(min(max(np.ceil(px + half - 0.5), 0.0), Wf))
        y1 = int(min(max(np.ceil(py + half - 0.5), 0.0), Hf))
    if y0 < ylo:
        y0 = ylo
    if y1 > yhi:
        y1 = yhi
    if x1 <= x0 or y1 <= y0:
        return
    _mark_box(tm, x0, y0, x1, y1, TW)
    wf = np.float32(w)
    if wf < _F0:
        wf = _F0
    key = (np.uint64(_f32_bits(wf)) << _U32) | np.uint64(logical)
    if not round_:
        # square: every pixel of the box; the 2x2 and 1x1 boxes of 2 px and 1 px points
        # unrolled, min() stores instead of a compare-and-branch (unpredictable)
        _store_box(kb, key, y0 * W + x0, x1 - x0, y1 - y0, W)
        return
    hh = half * half
    for yy in range(y0, y1):
        row = yy * W
        ey = yy + 0.5 - py
        for xx in range(x0, x1):
            if round_:
                ex = xx + 0.5 - px
                if ex * ex + ey * ey > hh:
                    continue
            i = row + xx
            kb[i] = min(key, kb[i])


#: points per block of the lean loops' vectorised first pass (:func:`_sq_block`): its nine
#: scratch rows (18 KB) stay in the core's first-level cache
SQ_BLOCK = 256
#: :func:`_sq_block`'s verdict per point (SQ_IN2: clearly inside, a 2x2 box)
SQ_OUT, SQ_IN, SQ_EDGE, SQ_BAD, SQ_IN2 = 0, 1, 2, 3, 4
#: the footprint LOD's smallest stride whose kept slots the lean loops gather (:func:`_sq_span`)
LOD_GATHER_FROM = 4


def _sq_block(pos, base, s0, n, step, X, Y, Z, code, bx0, by0, bx1, by1, bkey, bi, W, v00, v01, v02, v03, v10, v11,
              v12, v13, v20, v21, v22, v23, v30, v31, v32, v33, eps_s, half, Wf, Hf):
    """The per-point arithmetic of the lean loops for the n slots ``base + k step`` (logical
    ``s0 + k step``; step > 1: the footprint LOD's stride), with no branch, so that the
    compiler vectorises it: the positions copied into
    float64 rows first (contiguous), then per point the verdict (``code``: non-finite,
    clearly outside, clearly inside the frustum, or near a plane: the caller asks
    :func:`_frustum`), the clipped box and the key: the same float64 operations in the same
    order as the scalar code, lane by lane, so the same bits (values of points that are
    dropped are never read)."""
    if step == 1:
        for k in range(n):
            slot = np.uint64(base + k)
            X[k] = pos[slot, 0]
            Y[k] = pos[slot, 1]
            Z[k] = pos[slot, 2]
    else:
        for k in range(n):
            slot = np.uint64(base + k * step)
            X[k] = pos[slot, 0]
            Y[k] = pos[slot, 1]
            Z[k] = pos[slot, 2]
    for k in range(n):
        x = X[k]
        y = Y[k]
        z = Z[k]
        cx = v00 * x + v01 * y + v02 * z + v03
        cy = v10 * x + v11 * y + v12 * z + v13
        cz = v20 * x + v21 * y + v22 * z + v23
        w = v30 * x + v31 * y + v32 * z + v33
        e = eps_s * (abs(x) + abs(y) + abs(z) + 1.0)
        a0 = w + cx
        a1 = w - cx
        a2 = w + cy
        a3 = w - cy
        a5 = w - cz
        inside = (a0 > e) & (a1 > e) & (a2 > e) & (a3 > e) & (cz > e) & (a5 > e)
        me = -e
        outside = (a0 < me) | (a1 < me) | (a2 < me) | (a3 < me) | (cz < me) | (a5 < me)
        c = SQ_EDGE
        if outside:
            c = SQ_OUT
        if inside:
            c = SQ_IN
        if not (np.isfinite(x) & np.isfinite(y) & np.isfinite(z)):
            c = SQ_BAD
        px = (cx / w * 0.5 + 0.5) * Wf
        py = (0.5 - cy / w * 0.5) * Hf
        fx0 = min(max(np.ceil(px - half - 0.5), 0.0), Wf)
        fy0 = min(max(np.ceil(py - half - 0.5), 0.0), Hf)
        fx1 = min(max(np.ceil(px + half - 0.5), 0.0), Wf)
        fy1 = min(max(np.ceil(py + half - 0.5), 0.0), Hf)
        if (c == SQ_IN) & (fx1 - fx0 == 2.0) & (fy1 - fy0 == 2.0):  # compared as floats: NaN is no 2
            c = SQ_IN2
        code[k] = c
        x0 = int(fx0)
        y0 = int(fy0)
        bx0[k] = x0
        by0[k] = y0
        bx1[k] = int(fx1)
        by1[k] = int(fy1)
        bi[k] = y0 * W + x0
        wf = np.float32(w)
        if wf < _F0:
            wf = _F0
        bkey[k] = (np.uint64(_f32_bits(wf)) << _U32) | np.uint64(s0 + k)
    if step != 1:  # (a loop of its own: a 64-bit multiply in the loop above costs its vectorisation)
        for k in range(n):
            bkey[k] = (bkey[k] & _HI32) | np.uint64(s0 + k * step)


def _sq_scratch():
    """The rows :func:`_sq_block` fills for one block: positions (X, Y, Z), verdict, box
    (x0, y0, x1, y1), key and first pixel."""
    i64 = np.int64
    return (np.empty(SQ_BLOCK, np.float64), np.empty(SQ_BLOCK, np.float64), np.empty(SQ_BLOCK, np.float64),
            np.empty(SQ_BLOCK, i64), np.empty(SQ_BLOCK, i64), np.empty(SQ_BLOCK, i64), np.empty(SQ_BLOCK, i64),
            np.empty(SQ_BLOCK, i64), np.empty(SQ_BLOCK, np.uint64), np.empty(SQ_BLOCK, i64))


def _sq_keep(c, x, y, z, vp, planes, eps_s):
    """Whether a finite point with :func:`_sq_block`'s verdict ``c`` is kept: clearly inside
    yes, clearly outside no; near a plane, :func:`_frustum` decides (as the scalar loop)."""
    if c == SQ_IN or c == SQ_IN2:
        return True
    if c == SQ_OUT:
        return False
    cx = vp[0, 0] * x + vp[0, 1] * y + vp[0, 2] * z + vp[0, 3]
    cy = vp[1, 0] * x + vp[1, 1] * y + vp[1, 2] * z + vp[1, 3]
    cz = vp[2, 0] * x + vp[2, 1] * y + vp[2, 2] * z + vp[2, 3]
    w = vp[3, 0] * x + vp[3, 1] * y + vp[3, 2] * z + vp[3, 3]
    return _frustum(x, y, z, cx, cy, cz, w, planes, eps_s * (abs(x) + abs(y) + abs(z) + 1.0))


def _block_range(range_mode, code, Z, base, n, step, tms, cval, vmin, vmax):
    """The automatic colour range grown by the values of a block's finite points (non-finite
    values leave it), in loops of their own, point by point in the same order as before: the
    lean loops then take their fast path whatever the colour range mode."""
    if range_mode == C_Z:
        for k in range(n):
            if code[k] != SQ_BAD:
                vmin = min(vmin, Z[k])
                vmax = max(vmax, Z[k])
    elif range_mode != 0:
        for k in range(n):
            if range_mode == C_TIME:
                v = np.float64(tms[base + k * step])
            else:
                v = np.float64(cval[base + k * step])
            if code[k] != SQ_BAD and np.isfinite(v):
                vmin = min(vmin, v)
                vmax = max(vmax, v)
    return vmin, vmax


def _thinned(pos, tms, cval, base, n, m, range_mode, n_bad, vmin, vmax):
    """The slots of [base, base + n) the footprint LOD's mask ``m`` drops: counted (non-finite)
    and in the automatic colour range as every tier counts them, never projected."""
    for k in range(n):  # (a loop of its own: it runs over most of a far view's points)
        slot = base + k
        if (slot & m) != 0 and not (np.isfinite(pos[slot, 0]) & np.isfinite(pos[slot, 1]) & np.isfinite(pos[slot, 2])):
            n_bad += 1
    if range_mode != 0:
        for k in range(n):
            slot = base + k
            if (slot & m) != 0 and np.isfinite(pos[slot, 0]) and np.isfinite(pos[slot, 1]) and \
                    np.isfinite(pos[slot, 2]):
                v = _colour_value(range_mode, slot, pos, tms, cval)
                if np.isfinite(v):
                    vmin = min(vmin, v)
                    vmax = max(vmax, v)
    return n_bad, vmin, vmax


def _sq_span(blod, base, left):
    """A lean block from slot ``base`` with ``left`` slots to go: (slots it spans, the
    footprint LOD's mask there, the first kept slot's offset, slots to project, their step,
    the mask of the slots a small stride drops, whether the dropped ones are counted by the
    caller already). A block stays in one batch of slots, so one mask holds for it. A stride
    of :data:`LOD_GATHER_FROM` or more projects only the kept slots (the dropped ones are
    counted by :func:`_thinned`); a smaller one projects the block and drops the others'
    stores (measured cheaper than reading the block twice). A batch flagged
    :data:`~pointflow.render.batches.LOD_CPU_COUNTED` is counted from its bounds: every
    stride projects only its kept slots and its dropped ones are not read at all."""
    if blod.shape[0] == 0:
        n = min(left, SQ_BLOCK)
        return n, 0, 0, n, 1, 0, False
    w = np.int64(blod[base >> BATCH_SHIFT])
    counted = w >= LOD_CPU_COUNTED
    m = w & (LOD_CPU_COUNTED - 1)
    step = m + 1
    rem = (np.int64(1) << BATCH_SHIFT) - (base & ((np.int64(1) << BATCH_SHIFT) - 1))
    if step < LOD_GATHER_FROM and not (counted and step > 1):
        n = min(left, rem, SQ_BLOCK)
        return n, m, 0, n, 1, m, counted
    span = min(left, rem, SQ_BLOCK * step)
    k0 = (step - (base & m)) & m
    n = 0 if k0 >= span else (span - k0 + m) // step
    return span, m, k0, n, step, 0, counted


def _sq_next(blod, pos, tms, cval, s0, lb, off, range_mode, n_bad, vmin, vmax, sc, W, vs, eps_s, half, Wf, Hf):
    """The lean loops' next block from logical ``s0`` (slot ``s0 + off``) up to ``lb``
    (:func:`_sq_span`): the footprint LOD's dropped slots counted (:func:`_thinned`), the
    projected ones' arithmetic done into the scratch ``sc`` (:func:`_sq_block`) and their
    colour range taken; a small stride's dropped slots are marked :data:`SQ_OUT` (the
    per-point loop then passes them by as points off screen). Returns (the next block's s0,
    the slots projected, n_bad, vmin, vmax)."""
    X, Y, Z, code, bx0, by0, bx1, by1, bkey, bi = sc
    base = s0 + off
    span, m, k0, n, step, skip, counted = _sq_span(blod, base, lb - s0)
    if step > 1 and not counted:  # the footprint LOD's dropped slots: counted, not projected
        n_bad, vmin, vmax = _thinned(pos, tms, cval, base, span, m, range_mode, n_bad, vmin, vmax)
    if n > 0:
        _sq_block(pos, base + k0, s0 + k0, n, step, X, Y, Z, code, bx0, by0, bx1, by1, bkey, bi, W, vs[0], vs[1],
                  vs[2], vs[3], vs[4], vs[5], vs[6], vs[7], vs[8], vs[9], vs[10], vs[11], vs[12], vs[13], vs[14],
                  vs[15], eps_s, half, Wf, Hf)
        if counted:  # the whole batch's counts are the caller's (its bounds): none here
            for k in range(n):
                if code[k] == SQ_BAD:
                    code[k] = SQ_OUT
        else:
            vmin, vmax = _block_range(range_mode, code, Z, base + k0, n, step, tms, cval, vmin, vmax)
        if skip != 0:  # a small stride's dropped slots: never drawn (a non-finite one still counts)
            for k in range(n):
                if ((base + k) & skip) != 0 and code[k] != SQ_BAD:
                    code[k] = SQ_OUT
    return s0 + span, n, n_bad, vmin, vmax


def _chunk_sq(kb, tm, a, b, head, cap, pos, tms, cval, vp, planes, eps_s, W, H, half, range_mode, ylo, yhi, blod):
    """:func:`_raster`'s loop over logical [a, b) when no per-point test but the finite and
    frustum ones applies and the footprint is a screen-space square: the same decisions,
    bounds and keys, the arithmetic in blocks of :data:`SQ_BLOCK` points vectorised
    (:func:`_sq_block`: 0.56 of the scalar loop's time at 1M, one thread), then per point
    the branches and :func:`_splat`'s square stores, each box's tiles marked in ``tm`` (a 2x2
    box by its first pixel's: :func:`_tile_on`). Returns (occupied, non-finite, kept, vmin,
    vmax)."""
    v00, v01, v02, v03 = vp[0, 0], vp[0, 1], vp[0, 2], vp[0, 3]
    v10, v11, v12, v13 = vp[1, 0], vp[1, 1], vp[1, 2], vp[1, 3]
    v20, v21, v22, v23 = vp[2, 0], vp[2, 1], vp[2, 2], vp[2, 3]
    v30, v31, v32, v33 = vp[3, 0], vp[3, 1], vp[3, 2], vp[3, 3]
    Wf = np.float64(W)
    Hf = np.float64(H)
    n_bad = 0
    n_keep = 0
    vmin = np.inf
    vmax = -np.inf
    rows = ylo > 0 or yhi < H
    TW = _tile_grid(W, H)[0]
    sc = _sq_scratch()
    X, Y, Z, code, bx0, by0, bx1, by1, bkey, bi = sc
    vs = (v00, v01, v02, v03, v10, v11, v12, v13, v20, v21, v22, v23, v30, v31, v32, v33)
    for seg in range(2):  # the ring's two runs of slots: no wrap test per point
        if seg == 0:
            la, lb, off = a, min(b, cap - head), head
        else:
            la, lb, off = max(a, cap - head), b, head - cap
        s0 = la
        while s0 < lb:
            s0, n, n_bad, vmin, vmax = _sq_next(blod, pos, tms, cval, s0, lb, off, range_mode, n_bad, vmin, vmax,
                                                sc, W, vs, eps_s, half, Wf, Hf)
            for k in range(n):
                c = code[k]
                if c == SQ_IN2 and not rows:  # the common case: four stores
                    n_keep += 1
                    key = bkey[k]
                    i = bi[k]
                    kb[i] = min(key, kb[i])
                    kb[i + 1] = min(key, kb[i + 1])
                    kb[i + W] = min(key, kb[i + W])
                    kb[i + W + 1] = min(key, kb[i + W + 1])
                    tm[(by0[k] >> TILE_YS) * TW + (bx0[k] >> TILE_XS)] = 1
                    continue
                if c == SQ_BAD:
                    n_bad += 1
                    continue
                if not _sq_keep(c, X[k], Y[k], Z[k], vp, planes, eps_s):
                    continue
                n_keep += 1
                x0 = bx0[k]
                y0 = by0[k]
                x1 = bx1[k]
                y1 = by1[k]
                if rows:  # a band of the screen (split by bands)
                    if y0 < ylo:
                        y0 = ylo
                    if y1 > yhi:
                        y1 = yhi
                if x1 > x0 and y1 > y0:
                    _mark_box(tm, x0, y0, x1, y1, TW)
                _store_box(kb, bkey[k], y0 * W + x0, x1 - x0, y1 - y0, W)
    return b - a, n_bad, n_keep, vmin, vmax


def _raster(keys, marks, T, C, bands, st, vrange, mask, use_mask, pos, tms, imp, cval, head, size, cap, W, H, vp, planes,
            half_px, world, size_scale, round_, has_window, now_ms, window_ms, lod, blod, has_imp, imp_degenerate,
            imp_lo, imp_scale, seed_h, range_mode, eps_s):
    """T threads. ``bands`` (C = T): one key buffer, thread c owns rows [H c/T, H (c+1)/T),
    clears them and runs every point (counting only in thread 0). Else one key buffer per
    thread, and C chunks of logical indices handed out as threads come free (the caller sets
    a parallel chunk size of 1: a thread slowed by other work takes fewer chunks), each
    written into the buffer of the thread that runs it, which marks the tiles it writes in
    its row of ``marks``; a buffer's tiles its last frame marked (:func:`_tile_on`) are
    cleared first. Tests + splat (or splat the points ``mask`` keeps when ``use_mask``: the
    budget's passes did the tests). Counters per chunk in ``st``; the auto colour range in
    ``vrange``."""
    lean = not use_mask and not world and not round_ and not has_window and lod <= 1 and not has_imp
    TW, TH = _tile_grid(W, H)
    if not bands:
        for r in numba.prange(T * TH):
            t = r // TH
            ty = r - t * TH
            tm = marks[t]
            ya = ty << TILE_YS
            yb = min(ya + (1 << TILE_YS), H)
            for tx in range(TW):
                if _tile_on(tm, ty, tx, TW):
                    xa = tx << TILE_XS
                    xb = min(xa + (1 << TILE_XS), W)
                    for y in range(ya, yb):
                        for i in range(y * W + xa, y * W + xb):
                            keys[t, i] = EMPTY
        for t in numba.prange(T):
            marks[t, :] = 0
    for c in numba.prange(C):
        tm = marks[numba.get_thread_id()]
        if bands:
            kb = keys[0]
            ylo = H * c // T
            yhi = H * (c + 1) // T
            for i in range(ylo * W, yhi * W):
                kb[i] = EMPTY
            a = 0
            b = size
        else:
            kb = keys[numba.get_thread_id()]
            ylo = 0
            yhi = H
            a = size * c // C
            b = size * (c + 1) // C
        n_occ = 0
        n_bad = 0
        n_keep = 0
        n_drawn = 0
        vmin = np.inf
        vmax = -np.inf
        if lean:
            n_occ, n_bad, n_keep, vmin, vmax = _chunk_sq(kb, tm, a, b, head, cap, pos, tms, cval, vp, planes, eps_s, W, H,
                                                         half_px, range_mode, ylo, yhi, blod)
            n_drawn = n_keep
            a = b  # done: skip the general loop
        for logical in range(a, b):
            slot = head + logical
            if slot >= cap:
                slot -= cap
            if use_mask:
                if mask[logical] == 0:
                    continue
            else:
                n_occ += 1
                counted = blod.shape[0] != 0 and np.int64(blod[slot >> BATCH_SHIFT]) >= LOD_CPU_COUNTED
                if counted and (slot & np.int64(blod[slot >> BATCH_SHIFT])) != 0:
                    continue  # dropped by the footprint LOD, counted from its batch's bounds: never read
                if not (np.isfinite(pos[slot, 0]) and np.isfinite(pos[slot, 1]) and np.isfinite(pos[slot, 2])):
                    if not counted:
                        n_bad += 1
                    continue
                if range_mode != 0 and not counted:
                    v = _colour_value(range_mode, slot, pos, tms, cval)
                    if np.isfinite(v):
                        vmin = min(vmin, v)
                        vmax = max(vmax, v)
            x = np.float64(pos[slot, 0])
            y = np.float64(pos[slot, 1])
            z = np.float64(pos[slot, 2])
            cx = vp[0, 0] * x + vp[0, 1] * y + vp[0, 2] * z + vp[0, 3]
            cy = vp[1, 0] * x + vp[1, 1] * y + vp[1, 2] * z + vp[1, 3]
            w = vp[3, 0] * x + vp[3, 1] * y + vp[3, 2] * z + vp[3, 3]
            if not use_mask:
                cz = vp[2, 0] * x + vp[2, 1] * y + vp[2, 2] * z + vp[2, 3]
                if not _frustum(x, y, z, cx, cy, cz, w, planes, eps_s * (abs(x) + abs(y) + abs(z) + 1.0)):
                    continue
                if not _test(logical, slot, tms, imp, has_window, now_ms, window_ms, lod, blod, has_imp, imp_degenerate,
                             imp_lo, imp_scale, seed_h):
                    continue
                n_keep += 1
            _splat(kb, tm, TW, logical, cx, cy, w, W, H, half_px, world, size_scale, round_, ylo, yhi)
            n_drawn += 1
        if bands and c != 0:  # every band saw every point: count once
            n_occ = n_bad = n_keep = n_drawn = 0
            vmin = np.inf
            vmax = -np.inf
        st[c, ST_OCC] = n_occ
        st[c, ST_BAD] = n_bad
        st[c, ST_KEEP] = n_keep
        st[c, ST_DRAWN] = n_drawn
        vrange[c, 0] = vmin
        vrange[c, 1] = vmax


def _select(mask, st, vrange, pos, tms, imp, cval, head, size, cap, T, vp, planes, has_window, now_ms, window_ms, lod,
            blod, has_imp, imp_degenerate, imp_lo, imp_scale, seed_h, range_mode, eps_s):
    """The budget's first pass: the tests only, a keep flag per logical index."""
    for c in numba.prange(T):
        a = size * c // T
        b = size * (c + 1) // T
        n_occ = 0
        n_bad = 0
        n_keep = 0
        vmin = np.inf
        vmax = -np.inf
        for logical in range(a, b):
            slot = head + logical
            if slot >= cap:
                slot -= cap
            mask[logical] = 0
            n_occ += 1
            if not (np.isfinite(pos[slot, 0]) and np.isfinite(pos[slot, 1]) and np.isfinite(pos[slot, 2])):
                n_bad += 1
                continue
            if range_mode != 0:
                v = _colour_value(range_mode, slot, pos, tms, cval)
                if np.isfinite(v):
                    vmin = min(vmin, v)
                    vmax = max(vmax, v)
            x = np.float64(pos[slot, 0])
            y = np.float64(pos[slot, 1])
            z = np.float64(pos[slot, 2])
            cx = vp[0, 0] * x + vp[0, 1] * y + vp[0, 2] * z + vp[0, 3]
            cy = vp[1, 0] * x + vp[1, 1] * y + vp[1, 2] * z + vp[1, 3]
            cz = vp[2, 0] * x + vp[2, 1] * y + vp[2, 2] * z + vp[2, 3]
            w = vp[3, 0] * x + vp[3, 1] * y + vp[3, 2] * z + vp[3, 3]
            if not _frustum(x, y, z, cx, cy, cz, w, planes, eps_s * (abs(x) + abs(y) + abs(z) + 1.0)):
                continue
            if _test(logical, slot, tms, imp, has_window, now_ms, window_ms, lod, blod, has_imp, imp_degenerate, imp_lo,
                     imp_scale, seed_h):
                mask[logical] = 1
                n_keep += 1
        st[c, ST_OCC] = n_occ
        st[c, ST_BAD] = n_bad
        st[c, ST_KEEP] = n_keep
        vrange[c, 0] = vmin
        vrange[c, 1] = vmax


def _thin(mask, counts, head, size, cap, T, bseed, frac):
    """The budget's thinning: a survivor stays iff ``uniform01(slot, budget_seed) < frac``."""
    for c in numba.prange(T):
        a = size * c // T
        b = size * (c + 1) // T
        n = 0
        for logical in range(a, b):
            if mask[logical] == 0:
                continue
            slot = head + logical
            if slot >= cap:
                slot -= cap
            if _u01(slot, bseed) < frac:
                n += 1
            else:
                mask[logical] = 0
        counts[c] = n


def _cap(mask, base, size, T, budget):
    """Keep at most ``budget`` thinned survivors, the first in logical order (``base``: the
    thinned survivors before each chunk)."""
    for c in numba.prange(T):
        a = size * c // T
        b = size * (c + 1) // T
        run = base[c]
        for logical in range(a, b):
            if mask[logical] != 0:
                if run >= budget:
                    mask[logical] = 0
                run += 1


def _resolve_row(keys, marks, drawn, ty, W, H, fl, logz, edl, vp, head, cap, cmode, single, bg, rgbp, pos, tms, cval,
                 lo, scale, degenerate, lut):
    """A row of tiles of :func:`_resolve`. Per tile the buffers that may hold keys there
    (:func:`_tile_on`); none: the tile is background, written only if it was drawn last frame
    (``drawn``); else per pixel the smallest key over those buffers (the others are empty
    there: the same minimum) -> the winner's colour (or the background); with EDL, log2 of
    the winner's linear depth (clip w, float64 as the reference), +inf on the background."""
    T = keys.shape[0]
    TW = _tile_grid(W, H)[0]
    ya = ty << TILE_YS
    yb = min(ya + (1 << TILE_YS), H)
    for tx in range(TW):
        xa = tx << TILE_XS
        xb = min(xa + (1 << TILE_XS), W)
        c0 = -1
        c1 = -1
        n_on = 0
        for c in range(T):
            if _tile_on(marks[c], ty, tx, TW):
                if n_on == 0:
                    c0 = c
                elif n_on == 1:
                    c1 = c
                n_on += 1
        ti = ty * TW + tx
        if n_on == 0:
            if drawn[ti] != 0:
                for y in range(ya, yb):
                    for i in range(y * W + xa, y * W + xb):
                        fl[i] = bg
                        if edl:
                            logz[i] = np.inf
                drawn[ti] = 0
            continue
        drawn[ti] = 1
        for y in range(ya, yb):
            for i in range(y * W + xa, y * W + xb):  # the pixel's code written out here: a
                k = keys[c0, i]                       # function taking arrays cost ~40 ns a call
                if n_on == 2:
                    k = min(k, keys[c1, i])
                elif n_on > 2:
                    for c in range(c1, T):
                        k = min(k, keys[c, i])
                if k == EMPTY:
                    fl[i] = bg
                    if edl:
                        logz[i] = np.inf
                    continue
                slot = head + np.int64(k & _M32)
                if slot >= cap:
                    slot -= cap
                if edl:
                    w = (vp[3, 0] * np.float64(pos[slot, 0]) + vp[3, 1] * np.float64(pos[slot, 1])
                         + vp[3, 2] * np.float64(pos[slot, 2]) + vp[3, 3])
                    logz[i] = np.log2(w)
                if cmode == C_SINGLE:
                    fl[i] = single
                    continue
                if cmode == C_RGB:
                    fl[i] = rgbp[slot]
                    continue
                if cmode == C_Z:
                    v = pos[slot, 2]
                elif cmode == C_TIME:
                    v = np.float32(tms[slot])
                else:
                    v = cval[slot]
                if not np.isfinite(v):
                    fl[i] = single
                elif degenerate:
                    fl[i] = lut[255]
                else:
                    t = (v - lo) * scale
                    t = min(max(t, _F0), _F1)
                    fl[i] = lut[int(np.floor(t * _F255 + _FH))]


def _resolve(keys, marks, drawn, img, logz, edl, vp, head, cap, cmode, single, bg, rgbp, pos, tms, cval, lo, scale,
             degenerate, lut):
    """The image from the key buffers (:func:`_resolve_row` per row of tiles; picking reads
    the keys themselves). Compiled without ``parallel`` as ``resolve_1`` too, for frames
    drawn with one thread (the parallel build's overhead is not repaid there)."""
    H = img.shape[0]
    W = img.shape[1]
    fl = img.reshape(H * W)
    TH = _tile_grid(W, H)[1]
    for ty in numba.prange(TH):
        _resolve_row(keys, marks, drawn, ty, W, H, fl, logz, edl, vp, head, cap, cmode, single, bg, rgbp, pos, tms,
                     cval, lo, scale, degenerate, lut)


def _edl(logz, img, offsets, k_shade):
    """Eye-dome lighting (rules.edl_shade + rules.apply_shade) over the winners' log2 depth
    (+inf = background: contributes nothing, is not shaded)."""
    H = img.shape[0]
    W = img.shape[1]
    n = offsets.shape[0]
    for y in numba.prange(H):
        for x in range(W):
            i = y * W + x
            d = logz[i]
            if d == np.inf:
                continue
            resp = 0.0
            for k in range(n):
                qx = x + offsets[k, 0]
                qy = y + offsets[k, 1]
                if qx < 0 or qy < 0 or qx >= W or qy >= H:
                    continue
                e = d - logz[qy * W + qx]
                if e > 0.0:
                    resp += e
            resp /= n
            shade = np.exp(k_shade * resp)
            c = img[y, x]
            r = np.uint32(min(max(np.floor(np.float64(c & np.uint32(255)) * shade + 0.5), 0.0), 255.0))
            g = np.uint32(min(max(np.floor(np.float64((c >> np.uint32(8)) & np.uint32(255)) * shade + 0.5), 0.0), 255.0))
            bl = np.uint32(min(max(np.floor(np.float64((c >> np.uint32(16)) & np.uint32(255)) * shade + 0.5), 0.0), 255.0))
            img[y, x] = r | (g << np.uint32(8)) | (bl << np.uint32(16)) | (c & np.uint32(0xFF000000))


# --------------------------------------------------------------------------- binned raster (split "bins")
#: a box taller than this many bands goes to every band's shared bucket (bucket NB), once
MAX_BANDS_PER_POINT = 4
_M16 = np.uint64(0xFFFF)
_U16 = np.uint64(16)
_U48 = np.uint64(48)


def _box_pack(x0, x1, y0, y1):
    return np.uint64(x0) | (np.uint64(x1) << _U16) | (np.uint64(y0) << _U32) | (np.uint64(y1) << _U48)


def _bin_sq(sk, sb, cnt, a, b, head, cap, pos, tms, cval, vp, planes, eps_s, W, H, half, range_mode, BS, NB, blod):
    """:func:`_bin`'s loop over logical [a, b) when only the finite and frustum tests apply
    and the footprint is a screen-space square (as :func:`_chunk_sq`: the same decisions,
    boxes and keys, the arithmetic vectorised in blocks by :func:`_sq_block`). Returns
    (survivors, non-finite, vmin, vmax)."""
    v00, v01, v02, v03 = vp[0, 0], vp[0, 1], vp[0, 2], vp[0, 3]
    v10, v11, v12, v13 = vp[1, 0], vp[1, 1], vp[1, 2], vp[1, 3]
    v20, v21, v22, v23 = vp[2, 0], vp[2, 1], vp[2, 2], vp[2, 3]
    v30, v31, v32, v33 = vp[3, 0], vp[3, 1], vp[3, 2], vp[3, 3]
    Wf = np.float64(W)
    Hf = np.float64(H)
    n_bad = 0
    ns = 0
    vmin = np.inf
    vmax = -np.inf
    sc = _sq_scratch()
    X, Y, Z, code, bx0, by0, bx1, by1, bkey, bi = sc
    vs = (v00, v01, v02, v03, v10, v11, v12, v13, v20, v21, v22, v23, v30, v31, v32, v33)
    for seg in range(2):  # the ring's two runs of slots: no wrap test per point
        if seg == 0:
            la, lb, off = a, min(b, cap - head), head
        else:
            la, lb, off = max(a, cap - head), b, head - cap
        s0 = la
        while s0 < lb:
            s0, n, n_bad, vmin, vmax = _sq_next(blod, pos, tms, cval, s0, lb, off, range_mode, n_bad, vmin, vmax,
                                                sc, W, vs, eps_s, half, Wf, Hf)
            for k in range(n):
                c = code[k]
                if c == SQ_BAD:
                    n_bad += 1
                    continue
                if not _sq_keep(c, X[k], Y[k], Z[k], vp, planes, eps_s):
                    continue
                x0 = bx0[k]
                y0 = by0[k]
                x1 = bx1[k]
                y1 = by1[k]
                sk[ns] = bkey[k]
                sb[ns] = _box_pack(x0, x1, y0, y1)
                # an empty box (off screen) is kept, counted, and never binned
                if x1 > x0 and y1 > y0:
                    b0 = y0 >> BS
                    b1 = (y1 - 1) >> BS
                    if b0 == b1:
                        cnt[b0] += 1
                    elif b1 - b0 < MAX_BANDS_PER_POINT:
                        for j in range(b0, b1 + 1):
                            cnt[j] += 1
                    else:
                        cnt[NB] += 1
                ns += 1
    return ns, n_bad, vmin, vmax


def _bin(rkey, rbox, rf, off, need, st, vrange, ca, cb, cull, cbad, cvr, mask, use_mask, skey, sbox, sf, scur, pos, tms, imp, cval, head,
         size, cap, W, H, vp, planes, half_px, world, size_scale, round_, has_window, now_ms, window_ms, lod, blod, has_imp,
         imp_degenerate, imp_lo, imp_scale, seed_h, range_mode, eps_s, L, RC, BS, NB):
    """Pass 1 of the binned raster: chunks of logical indices ``[ca[c], cb[c])`` (at most
    ``L``; each within one batch of slots), handed to threads as they come free. A chunk with
    ``cull[c]`` (a whole batch whose bounds lie outside the frustum) touches no point: its
    counts are the batch's (``cbad``: non-finite; ``cvr``: the colour value's range). Per point the rules, the float64 projection, the footprint box
    (rules.footprint_box, clipped to the screen) and the key, into the thread's scratch
    (``skey``/``sbox``/``sf``: L entries, in cache); then the chunk's survivors counting-sorted
    by screen band (rows [BH j, BH (j + 1)), BH = 2^BS) into its own region of the records
    (``[c RC, (c + 1) RC)``): one record per band the box touches, or one in bucket ``NB`` when
    it touches more than MAX_BANDS_PER_POINT bands. ``off[c, j]`` is where band j starts
    (``off[c, NB + 1]`` the end); ``need[c]`` the records the chunk needs (> RC: nothing
    written, the caller grows RC and runs again). No shared writes."""
    C = off.shape[0]
    v00, v01, v02, v03 = vp[0, 0], vp[0, 1], vp[0, 2], vp[0, 3]
    v10, v11, v12, v13 = vp[1, 0], vp[1, 1], vp[1, 2], vp[1, 3]
    v20, v21, v22, v23 = vp[2, 0], vp[2, 1], vp[2, 2], vp[2, 3]
    v30, v31, v32, v33 = vp[3, 0], vp[3, 1], vp[3, 2], vp[3, 3]
    Wf = np.float64(W)
    Hf = np.float64(H)
    lean = not use_mask and not world and not round_ and not has_window and lod <= 1 and not has_imp
    for c in numba.prange(C):
        tid = numba.get_thread_id()
        sk = skey[tid]
        sb = sbox[tid]
        cnt = scur[tid]
        for j in range(NB + 2):
            cnt[j] = 0
        a = ca[c]
        b = cb[c]
        if cull[c]:
            st[c, ST_OCC] = b - a
            st[c, ST_BAD] = cbad[c]
            st[c, ST_KEEP] = 0
            st[c, ST_DRAWN] = 0
            vrange[c, 0] = cvr[c, 0] if range_mode != 0 else np.inf
            vrange[c, 1] = cvr[c, 1] if range_mode != 0 else -np.inf
            need[c] = 0
            for j in range(NB + 2):
                off[c, j] = c * RC
            continue
        n_occ = 0
        n_bad = 0
        n_keep = 0
        ns = 0
        vmin = np.inf
        vmax = -np.inf
        if lean:
            ns, n_bad, vmin, vmax = _bin_sq(sk, sb, cnt, a, b, head, cap, pos, tms, cval, vp, planes, eps_s, W, H,
                                            half_px, range_mode, BS, NB, blod)
            n_occ = b - a
            n_keep = ns
            a = b  # done: skip the general loop
        for seg in range(2):  # the ring's two runs of slots: no wrap test per point
            if seg == 0:
                la, lb, soff = a, min(b, cap - head), head
            else:
                la, lb, soff = max(a, cap - head), b, head - cap
            for logical in range(la, lb):
                slot = logical + soff
                if use_mask:
                    if mask[logical] == 0:
                        continue
                counted = not use_mask and blod.shape[0] != 0 and \
                    np.int64(blod[slot >> BATCH_SHIFT]) >= LOD_CPU_COUNTED
                if counted and (slot & np.int64(blod[slot >> BATCH_SHIFT])) != 0:
                    n_occ += 1
                    continue  # dropped by the footprint LOD, counted from its batch's bounds: never read
                x = np.float64(pos[slot, 0])
                y = np.float64(pos[slot, 1])
                z = np.float64(pos[slot, 2])
                if not use_mask:
                    n_occ += 1
                    if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
                        if not counted:
                            n_bad += 1
                        continue
                    if range_mode != 0 and not counted:
                        v = _colour_value(range_mode, slot, pos, tms, cval)
                        if np.isfinite(v):
                            vmin = min(vmin, v)
                            vmax = max(vmax, v)
                cx = v00 * x + v01 * y + v02 * z + v03
                cy = v10 * x + v11 * y + v12 * z + v13
                w = v30 * x + v31 * y + v32 * z + v33
                if not use_mask:
                    cz = v20 * x + v21 * y + v22 * z + v23
                    if not _frustum(x, y, z, cx, cy, cz, w, planes, eps_s * (abs(x) + abs(y) + abs(z) + 1.0)):
                        continue
                    if not _test(logical, slot, tms, imp, has_window, now_ms, window_ms, lod, blod, has_imp,
                                 imp_degenerate, imp_lo, imp_scale, seed_h):
                        continue
                n_keep += 1
                px = (cx / w * 0.5 + 0.5) * W
                py = (0.5 - cy / w * 0.5) * H
                half = half_px
                if world:
                    s = size_scale / w
                    if s < 1.0:
                        s = 1.0
                    if s > 4096.0:
                        s = 4096.0
                    half = s * 0.5
                x0 = int(min(max(np.ceil(px - half - 0.5), 0.0), Wf))
                y0 = int(min(max(np.ceil(py - half - 0.5), 0.0), Hf))
                if round_:
                    x1 = int(min(max(np.floor(px + half - 0.5) + 1.0, 0.0), Wf))
                    y1 = int(min(max(np.floor(py + half - 0.5) + 1.0, 0.0), Hf))
                else:
                    x1 = int(min(max(np.ceil(px + half - 0.5), 0.0), Wf))
                    y1 = int(min(max(np.ceil(py + half - 0.5), 0.0), Hf))
                if x1 <= x0 or y1 <= y0:
                    continue
                wf = np.float32(w)
                if wf < _F0:
                    wf = _F0
                sk[ns] = (np.uint64(_f32_bits(wf)) << _U32) | np.uint64(logical)
                sb[ns] = _box_pack(x0, x1, y0, y1)
                if round_:
                    sf[tid, ns, 0] = px
                    sf[tid, ns, 1] = py
                    sf[tid, ns, 2] = half
                ns += 1
                b0 = y0 >> BS
                b1 = (y1 - 1) >> BS
                if b1 - b0 < MAX_BANDS_PER_POINT:
                    for j in range(b0, b1 + 1):
                        cnt[j] += 1
                else:
                    cnt[NB] += 1
        total = 0
        for j in range(NB + 1):
            total += cnt[j]
        need[c] = total
        st[c, ST_OCC] = n_occ
        st[c, ST_BAD] = n_bad
        st[c, ST_KEEP] = n_keep
        st[c, ST_DRAWN] = n_keep
        vrange[c, 0] = vmin
        vrange[c, 1] = vmax
        if total > RC:
            continue  # overflow: the caller grows RC and runs the pass again
        run = c * RC
        for j in range(NB + 1):
            k = cnt[j]
            off[c, j] = run
            cnt[j] = run
            run += k
        off[c, NB + 1] = run
        for i in range(ns):
            bx = sb[i]
            y0 = np.int64((bx >> _U32) & _M16)
            y1 = np.int64(bx >> _U48)
            x0 = np.int64(bx & _M16)
            x1 = np.int64((bx >> _U16) & _M16)
            if y1 <= y0 or x1 <= x0:
                continue  # off screen (the lean loop keeps these in the scratch)
            b0 = y0 >> BS
            b1 = (y1 - 1) >> BS
            if b1 - b0 >= MAX_BANDS_PER_POINT:
                b0 = NB
                b1 = NB
            for j in range(b0, b1 + 1):
                r = cnt[j]
                cnt[j] = r + 1
                rkey[r] = sk[i]
                if round_ or j == NB:
                    rbox[r] = bx
                    if round_:
                        rf[r, 0] = sf[tid, i, 0]
                        rf[r, 1] = sf[tid, i, 1]
                        rf[r, 2] = sf[tid, i, 2]
                else:  # a square in band j: its part of the band, as (index in the band, dx, dy)
                    top = j << BS
                    ya = max(y0, top) - top
                    yb = min(y1, top + (np.int64(1) << BS)) - top
                    rbox[r] = np.uint64(ya * W + x0) | (np.uint64(x1 - x0) << _U32) | (np.uint64(yb - ya) << _U48)


def _batch_stats(ks, B, cap, pos, tms, cval, cmode, lo, hi, bad, vlo, vhi):
    """Per batch k in ``ks`` (slots [k B, min((k + 1) B, cap))): the bounds of its finite
    positions (``lo``/``hi``; +inf/-inf when none), its non-finite count, and the range of the
    colour value (mode ``cmode``) over its finite points, as the raster pass reduces it."""
    for q in numba.prange(ks.shape[0]):
        k = ks[q]
        x0 = y0 = z0 = np.inf
        x1 = y1 = z1 = -np.inf
        vmin = np.inf
        vmax = -np.inf
        n_bad = 0
        for slot in range(k * B, min((k + 1) * B, cap)):
            x = np.float64(pos[slot, 0])
            y = np.float64(pos[slot, 1])
            z = np.float64(pos[slot, 2])
            if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
                n_bad += 1
                continue
            x0 = min(x0, x)
            x1 = max(x1, x)
            y0 = min(y0, y)
            y1 = max(y1, y)
            z0 = min(z0, z)
            z1 = max(z1, z)
            if cmode >= C_SCALAR:
                v = _colour_value(cmode, slot, pos, tms, cval)
                if np.isfinite(v):
                    vmin = min(vmin, v)
                    vmax = max(vmax, v)
        lo[k, 0] = x0
        lo[k, 1] = y0
        lo[k, 2] = z0
        hi[k, 0] = x1
        hi[k, 1] = y1
        hi[k, 2] = z1
        bad[k] = n_bad
        vlo[k] = vmin
        vhi[k] = vmax


def _band_splat(kb, row0, ylo, yhi, ra, rb, rkey, rbox, rf, W, round_):
    """Full-box records [ra, rb) (round points, and boxes over many bands) into ``kb`` (rows
    [row0, ...) of the screen), clipped to rows [ylo, yhi): the smallest key per pixel
    (square: every pixel of the box; round: the pixels whose centre lies within half of
    (px, py), as :func:`_splat`)."""
    for r in range(ra, rb):
        bx = rbox[r]
        y0 = np.int64((bx >> _U32) & _M16)
        y1 = np.int64(bx >> _U48)
        if y0 < ylo:
            y0 = ylo
        if y1 > yhi:
            y1 = yhi
        if y1 <= y0:
            continue
        x0 = np.int64(bx & _M16)
        x1 = np.int64((bx >> _U16) & _M16)
        key = rkey[r]
        if not round_:
            for yy in range(y0, y1):
                row = (yy - row0) * W
                for xx in range(x0, x1):
                    kb[row + xx] = min(key, kb[row + xx])
            continue
        px = rf[r, 0]
        py = rf[r, 1]
        half = rf[r, 2]
        hh = half * half
        for yy in range(y0, y1):
            row = (yy - row0) * W
            ey = yy + 0.5 - py
            for xx in range(x0, x1):
                ex = xx + 0.5 - px
                if ex * ex + ey * ey > hh:
                    continue
                kb[row + xx] = min(key, kb[row + xx])


def _band_splat_sq(kb, ra, rb, rkey, rbox, W):
    """Square records [ra, rb) of one band (index in the band, dx, dy) into its keys ``kb``
    (:func:`_store_box`)."""
    for r in range(ra, rb):
        p = rbox[r]
        _store_box(kb, rkey[r], np.int64(p & _M32), np.int64((p >> _U32) & _M16), np.int64(p >> _U48), W)


def _band_fill(kb, j, H, W, BS, NB, rkey, rbox, rf, off, round_):
    """The smallest key of every pixel of band j (rows [j 2^BS, (j + 1) 2^BS)) into ``kb``,
    from the band's records of every chunk and the shared bucket. Returns the band's rows."""
    C = off.shape[0]
    ylo = j << BS
    yhi = min(ylo + (np.int64(1) << BS), H)
    for i in range((yhi - ylo) * W):
        kb[i] = EMPTY
    for c in range(C):
        if round_:
            _band_splat(kb, ylo, ylo, yhi, off[c, j], off[c, j + 1], rkey, rbox, rf, W, round_)
        else:
            _band_splat_sq(kb, off[c, j], off[c, j + 1], rkey, rbox, W)
    for c in range(C):
        _band_splat(kb, ylo, ylo, yhi, off[c, NB], off[c, NB + 1], rkey, rbox, rf, W, round_)
    return ylo, yhi


def _band(kb, j, fl, logz, edl, rkey, rbox, rf, off, W, H, BS, NB, round_, vp, head, cap, cmode, single, bg, rgbp,
          pos, tms, cval, lo, scale, degenerate, lut):
    """One band of :func:`_bands`: its keys (:func:`_band_fill`), then per pixel the winner's
    colour (as :func:`_resolve`). A function of its own, not inlined into the parallel loop
    (numba's parallel build of the per-pixel loop runs at about half the speed)."""
    ylo, yhi = _band_fill(kb, j, H, W, BS, NB, rkey, rbox, rf, off, round_)
    base = ylo * W
    n = (yhi - ylo) * W
    if cmode == C_SCALAR and not edl:  # the commonest case, without the per-pixel branches
        for i in range(n):
            k = kb[i]
            if k == EMPTY:
                fl[base + i] = bg
                continue
            slot = head + np.int64(k & _M32)
            if slot >= cap:
                slot -= cap
            v = cval[slot]
            if not np.isfinite(v):
                fl[base + i] = single
            elif degenerate:
                fl[base + i] = lut[255]
            else:
                t = (v - lo) * scale
                t = min(max(t, _F0), _F1)
                fl[base + i] = lut[int(np.floor(t * _F255 + _FH))]
        return
    for i in range(n):
        k = kb[i]
        p = base + i
        if k == EMPTY:
            fl[p] = bg
            if edl:
                logz[p] = np.inf
            continue
        slot = head + np.int64(k & _M32)
        if slot >= cap:
            slot -= cap
        if edl:
            w = (vp[3, 0] * np.float64(pos[slot, 0]) + vp[3, 1] * np.float64(pos[slot, 1])
                 + vp[3, 2] * np.float64(pos[slot, 2]) + vp[3, 3])
            logz[p] = np.log2(w)
        if cmode == C_SINGLE:
            fl[p] = single
        elif cmode == C_RGB:
            fl[p] = rgbp[slot]
        else:
            if cmode == C_Z:
                v = pos[slot, 2]
            elif cmode == C_TIME:
                v = np.float32(tms[slot])
            else:
                v = cval[slot]
            if not np.isfinite(v):
                fl[p] = single
            elif degenerate:
                fl[p] = lut[255]
            else:
                t = (v - lo) * scale
                t = min(max(t, _F0), _F1)
                fl[p] = lut[int(np.floor(t * _F255 + _FH))]


def _bands(kbuf, img, logz, edl, rkey, rbox, rf, off, W, H, BS, NB, round_, vp, head, cap, cmode, single, bg, rgbp,
           pos, tms, cval, lo, scale, degenerate, lut):
    """Pass 2 of the binned raster: bands handed to threads as they come free; each thread
    keys its band in its own buffer (``kbuf[thread]``, 2^BS rows: in cache) and resolves it into
    the image (:func:`_band`). No shared writes, no full-screen key buffer, no merge."""
    fl = img.reshape(H * W)
    for jj in numba.prange(NB):
        _band(kbuf[numba.get_thread_id()], np.int64(jj), fl, logz, edl, rkey, rbox, rf, off, W, H, np.int64(BS), NB,
              round_, vp, head, cap, cmode, single, bg, rgbp, pos, tms, cval, lo, scale, degenerate, lut)


def _keys_rows(out, kb, ylo, yhi, rkey, rbox, rf, off, W, H, BS, NB, round_):
    """The last binned frame's smallest key per pixel of rows [ylo, yhi) (picking): the
    bands they cross keyed again in ``kb``, their rows copied out."""
    for j in range(ylo >> BS, ((yhi - 1) >> BS) + 1):
        a, b = _band_fill(kb, j, H, W, BS, NB, rkey, rbox, rf, off, round_)
        for y in range(max(a, ylo), min(b, yhi)):
            for x in range(W):
                out[(y - ylo) * W + x] = kb[(y - a) * W + x]


_F32_BITS_PY = _f32_bits

# --------------------------------------------------------------------------- compilation
class Kernels:
    """The compiled loops (attributes named as the functions above, without the underscore)."""

    def __init__(self, **fns: Any):
        self.__dict__.update(fns)


numba: Any = None
_kernels: Optional[Kernels] = None
_why: str = ""
_tried = False
_lock = threading.Lock()


#: OpenMP's idle workers sleep at once instead of spinning (libgomp reads this when numba
#: starts its ``omp`` threading layer, at the first parallel loop): spinning workers took the
#: cores from the caller's own thread and from the other stages (ingest, cadence) on a shared
#: machine, and made two threads slower than one; a value the user set is kept
OMP_WAIT_POLICY = "PASSIVE"


def _compile(cache: bool) -> Kernels:
    global numba
    os.environ.setdefault("OMP_WAIT_POLICY", OMP_WAIT_POLICY)
    import numba as nb

    numba = nb  # the loops name numba.prange through this module global
    g = globals()
    opts = dict(cache=cache, nogil=True, boundscheck=False, error_model="numpy")
    from numba.extending import intrinsic
    g["_f32_bits"] = intrinsic(_F32_BITS_PY)
    for name in ("_pcg", "_u01", "_colour_value", "_frustum", "_test", "_store_box", "_splat", "_box_pack",
                 "_tile_grid", "_tile_on", "_mark_box",
                 "_band_splat", "_band_splat_sq", "_band_fill", "_sq_keep", "_block_range",
                 "_sq_scratch", "_sq_span"):
        g[name] = nb.njit(inline="always", **opts)(g[name])
    # called from parallel loops, each compiled on its own (numba's inliner takes no functions
    # with as many arguments as _sq_block)
    for name in ("_sq_block", "_thinned", "_sq_next", "_band", "_bin_sq", "_chunk_sq", "_resolve_row"):
        g[name] = nb.njit(**opts)(g[name])
    out = {}
    for name in ("_raster", "_select", "_thin", "_cap", "_resolve", "_edl", "_bin", "_bands",
                 "_batch_stats"):
        out[name[1:]] = nb.njit(parallel=True, **opts)(g[name])
    out["resolve_1"] = nb.njit(**opts)(g["_resolve"])  # one thread: prange runs as range
    out["keys_rows"] = nb.njit(**opts)(g["_keys_rows"])
    return Kernels(**out)


#: the loops a render stage runs: all cached = ready
REQUIRED = ("raster", "select", "thin", "cap", "resolve", "edl", "resolve_1", "bin", "bands", "batch_stats",
            "keys_rows")


def dispatchers() -> list:
    """The dispatchers of :data:`REQUIRED` (creating them compiles nothing), or [] without numba."""
    k = load()
    return [getattr(k, n) for n in REQUIRED] if k is not None else []


def cache_state() -> str:
    """Whether the loops can start without compiling (:func:`pointflow.jitcache.state`):
    ``ready``, ``missing`` (a compile is due), ``unwritable`` (numba has nowhere to cache
    them), or ``unavailable`` (numba missing or off)."""
    from .. import jitcache

    ds = dispatchers()
    return jitcache.state(ds) if ds else "unavailable"


def cache_dir() -> Optional[str]:
    """Where numba caches the loops (``NUMBA_CACHE_DIR`` first), or None."""
    from .. import jitcache

    return jitcache.cache_dir(dispatchers())


def disabled() -> Optional[str]:
    """Why the compiled method is off by request (``POINTFLOW_NO_NUMBA``), or None."""
    if os.environ.get(ENV_NO_NUMBA, "") not in ("", "0"):
        return f"${ENV_NO_NUMBA}={os.environ[ENV_NO_NUMBA]}"
    return None


def load() -> Optional[Kernels]:
    """The compiled loops, or None (numba missing or disabled; :func:`why_unavailable` says why)."""
    global _kernels, _tried, _why
    if _tried:
        return _kernels
    with _lock:
        if _tried:
            return _kernels
        off = disabled()
        if off:
            _why = f"{off} turns compiled loops off"
        else:
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # a cache that cannot be written is not the user's problem
                    try:
                        _kernels = _compile(cache=True)
                    except Exception as exc:  # noqa: BLE001 - e.g. no writable cache location
                        log.info("cpu raster: compiled without a disk cache (%s: %s)", type(exc).__name__, exc)
                        _kernels = _compile(cache=False)
            except Exception as exc:  # noqa: BLE001 - numba missing or broken
                _why = f"numba unavailable ({type(exc).__name__}: {exc})"
                _kernels = None
        _tried = True
        return _kernels


def why_unavailable() -> str:
    return _why


def available() -> bool:
    """True when numba can be imported and is not disabled (without compiling anything)."""
    if disabled():
        return False
    try:
        import importlib.util
        return importlib.util.find_spec("numba") is not None
    except (ImportError, ValueError):
        return False
