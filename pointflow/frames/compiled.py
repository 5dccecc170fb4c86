"""The rigid transform as one compiled loop (numba), for the ring's write of a placed cloud.

Why: numpy has no fused "float32 in, float64 ``R p + v``, float32 out"; it takes a float64
copy, a BLAS product (OpenBLAS's worst shape, K = 3), a translation pass and a rounding copy:
about 7.6 ns per point on the shared 2-core VM. The loop below reads each point once, does
the nine products and three sums in float64 and rounds once to float32: about 1.9 ns per
point (bench/bench_frames.py). No fast-math: the arithmetic is IEEE float64 as written
(no FMA contraction, no reordering), so it equals numpy's answer up to the summation order
inside BLAS (an ulp of the float64 result, then the same float32 rounding in nearly all
cases; tests/ring/test_transform_push.py and tests/frames/test_compiled.py compare).

Loaded on first use (:func:`load`), not at import: importing numba and loading the cached
machine code costs about 0.5-1 s of CPU, which only a pipeline with ``frames.fixed`` should
pay (ingest's ``prepare`` does it in a standby, before it is needed). The compiled code is
cached on disk (``cache=True``: numba's own locations, ``NUMBA_CACHE_DIR`` first;
``pointflow warm`` fills it ahead). Compiling takes 2-3 s on an idle 2-core machine, so a
cache that does not hold the loops yet is filled by a compiler process of its own
(:mod:`pointflow.jitcache`) while the caller uses the numpy path
(:func:`pointflow.frames.kernels.rigid`: same results, slower), until the loops are cached;
with no writable cache location, or numba missing or failing, numpy it stays.
``POINTFLOW_NO_NUMBA=1`` forces that fallback (tests compare both).
"""
from __future__ import annotations

import logging
import os
import threading
import warnings
from typing import Any, Callable, NamedTuple, Optional

log = logging.getLogger("pointflow.frames")

#: float32 or float64 points as sent (flat, contiguous), float32 ring slots (flat, contiguous)
SRC_DTYPES = ("float32", "float64")


class Kernels(NamedTuple):
    """The compiled loops: ``rigid(src_flat, R, v, dst_flat)`` into float32 slots, ``rigid64``
    the same loop into float64, ``table(pos, idx, M, out)`` and ``nodes(pos, off, node0, inv_step, M, D, out)``
    (deskew.py's two paths)."""

    rigid: Callable
    rigid64: Callable
    table: Callable
    nodes: Callable


_lock = threading.Lock()
_kernel: Any = None
_tried = False


def _rigid_into(src, M, v, dst):  # pragma: no cover - runs compiled
    """dst[3i + r] = sum_j M[r, j] * float64(src[3i + j]) + v[r], left to right, rounded once
    to dst's type: float32 for the ring's slots, float64 for the placed positions that
    recording, thinning and small clouds of a dynamic chain need."""
    n = src.shape[0] // 3
    m00, m01, m02 = M[0, 0], M[0, 1], M[0, 2]
    m10, m11, m12 = M[1, 0], M[1, 1], M[1, 2]
    m20, m21, m22 = M[2, 0], M[2, 1], M[2, 2]
    v0, v1, v2 = v[0], v[1], v[2]
    for i in range(n):
        k = 3 * i
        x = float(src[k])
        y = float(src[k + 1])
        z = float(src[k + 2])
        dst[k] = m00 * x + m01 * y + m02 * z + v0
        dst[k + 1] = m10 * x + m11 * y + m12 * z + v1
        dst[k + 2] = m20 * x + m21 * y + m22 * z + v2


def _table_into_f64(pos, idx, M, out):  # pragma: no cover - runs compiled
    """deskew.apply_table's loop: point i with pose column idx[i] of M (12, U): r00 r01 .. r22
    tx ty tz; the sums in numpy's order (t + r0 x + r1 y + r2 z, left to right): bit for bit
    the numpy path's answer."""
    for i in range(pos.shape[0]):
        u = idx[i]
        x = float(pos[i, 0])
        y = float(pos[i, 1])
        z = float(pos[i, 2])
        out[i, 0] = M[9, u] + M[0, u] * x + M[1, u] * y + M[2, u] * z
        out[i, 1] = M[10, u] + M[3, u] * x + M[4, u] * y + M[5, u] * z
        out[i, 2] = M[11, u] + M[6, u] * x + M[7, u] * y + M[8, u] * z


def _nodes_into_f64(pos, off, node0, inv_step, M, D, out):  # pragma: no cover - runs compiled
    """deskew.apply_nodes's loop: the pose linearly interpolated between the two nodes around
    each point's time (M: node poses (12, K), D: differences to the next node); the same
    operations in the same order as the numpy path."""
    k = M.shape[1]
    hi = float(k - 1)
    for i in range(pos.shape[0]):
        f = (off[i] - node0) * inv_step
        if not f >= 0.0:  # also NaN (the frames step passes finite times only): no wild index
            f = 0.0
        elif f > hi:
            f = hi
        j = int(f)
        if j > k - 2:
            j = k - 2
        f -= j
        x = float(pos[i, 0])
        y = float(pos[i, 1])
        z = float(pos[i, 2])
        for r in range(3):
            a = M[9 + r, j] + M[3 * r, j] * x + M[3 * r + 1, j] * y + M[3 * r + 2, j] * z
            b = D[9 + r, j] + D[3 * r, j] * x + D[3 * r + 1, j] * y + D[3 * r + 2, j] * z
            out[i, r] = a + b * f


def _compile(cache: bool) -> Callable:
    import numba
    from numba import types

    def arr(dt, nd, readonly):
        return types.Array(getattr(types, dt), nd, "C", readonly=readonly)

    # inputs typed read-only: received frames may be read-only bytes; writable arrays convert
    sigs = [types.void(arr(dt, 1, True), arr("float64", 2, True), arr("float64", 1, True), arr(out, 1, False))
            for dt in SRC_DTYPES for out in ("float32", "float64")]
    rigid = numba.njit(sigs, cache=cache, nogil=True, boundscheck=False)(_rigid_into)
    table = numba.njit([types.void(arr(dt, 2, True), arr("intp", 1, True), arr("float64", 2, True), arr("float64", 2, False))
                        for dt in SRC_DTYPES], cache=cache, nogil=True, boundscheck=False)(_table_into_f64)
    nodes = numba.njit([types.void(arr(dt, 2, True), arr("float64", 1, True), types.float64, types.float64,
                                   arr("float64", 2, True), arr("float64", 2, True), arr("float64", 2, False))
                        for dt in SRC_DTYPES], cache=cache, nogil=True, boundscheck=False)(_nodes_into_f64)
    return Kernels(rigid, rigid, table, nodes)  # one loop, float32 or float64 out


def compile_all(dispatchers_only: bool = False) -> list:
    """The compile-ahead target (:mod:`pointflow.jitcache`, ``pointflow warm``): compile every
    signature into numba's disk cache; returns dispatchers of the three loops (made lazily:
    ``dispatchers_only`` compiles nothing) for :func:`pointflow.jitcache.state`."""
    import numba

    if not dispatchers_only:
        _compile(cache=True)
    return [numba.njit(cache=True, nogil=True, boundscheck=False)(f) for f in (_rigid_into, _table_into_f64, _nodes_into_f64)]


#: how often a load() that waits for the background compiler looks again
_POLL_S = 0.5
_pending: Optional[str] = None  # the cache directory a background compiler fills
_proc: Any = None  # the compiler this process started
_next_look = 0.0


def _first_load() -> Optional[Kernels]:
    """The first :func:`load`: the cached loops when numba's cache holds them; else None now
    (numpy draws the same points, slower) and a compiler fills the cache in a process of its
    own (:mod:`pointflow.jitcache`), so ingest never waits for it."""
    global _pending
    from .. import jitcache

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = compile_all(dispatchers_only=True)
        st = jitcache.state(ds)
        if st == jitcache.READY:
            try:
                return _compile(cache=True)
            except Exception as exc:  # noqa: BLE001 - e.g. the cache went away since: compile here
                log.info("frames: compiled transform without a disk cache (%s: %s)", type(exc).__name__, exc)
                return _compile(cache=False)
        where = jitcache.cache_dir(ds)
        if st == jitcache.UNWRITABLE or where is None:
            log.warning("frames: numba cannot cache the compiled transform (no writable location; set "
                        "NUMBA_CACHE_DIR and run `pointflow warm`); using numpy")
            return None
        if not jitcache.compiling(where):
            global _proc
            _proc = jitcache.start_compiler("pointflow.frames.compiled:compile_all", where)
        log.info("frames: compiling the transform loops in the background (first run on this machine); "
                 "numpy meanwhile")
        _pending = where
        return None


def _look_again() -> Optional[Kernels]:
    """While the background compiler works: None; then the compiled loops (or None for good)."""
    global _pending, _next_look, _kernel
    import time

    from .. import jitcache

    now = time.monotonic()
    if now < _next_look or _pending is None:
        return None
    _next_look = now + _POLL_S
    if (_proc is not None and _proc.poll() is None) or jitcache.compiling(_pending):
        return None  # ours still runs (it may not hold the lock yet), or another one's does
    where, _pending = _pending, None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if jitcache.state(compile_all(dispatchers_only=True)) != jitcache.READY:
            res = jitcache.last_result(where) or {}
            log.warning("frames: the transform loops could not be compiled (%s); using numpy",
                        res.get("message", "no result"))
            return None
        _kernel = _compile(cache=True)
    log.info("frames: transform loops compiled; using them from now on")
    return _kernel


def load() -> Optional[Kernels]:
    """The compiled loops (:class:`Kernels`), or None (numpy fallback: not compiled yet, or
    not available). The first call imports numba and loads the cached machine code, or
    starts compiling it beside the caller (:func:`_first_load`); later calls pick the loops
    up once compiled."""
    global _kernel, _tried
    if _tried:
        if _kernel is None and _pending is not None:
            with _lock:
                return _look_again() if _kernel is None else _kernel
        return _kernel
    with _lock:
        if _tried:
            return _kernel
        if os.environ.get("POINTFLOW_NO_NUMBA", "") not in ("", "0"):
            _tried = True
            return None
        try:
            _kernel = _first_load()
        except Exception as exc:  # noqa: BLE001 - numba missing or broken: numpy does the same, slower
            log.warning("frames: compiled transform unavailable (%s: %s); using numpy", type(exc).__name__, exc)
            _kernel = None
        _tried = True
        return _kernel
