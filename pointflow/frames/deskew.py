"""Motion compensation: each point transformed with the pose at its own capture time.

Per-point time conventions (``frames.deskew: auto`` picks by field name and dtype):

=============  ===========  ===================================  ===================
field          dtype        meaning                              driver
=============  ===========  ===================================  ===================
``t``          uint32       ns after the header stamp            Ouster
``time``       float32      s relative to the header stamp       Velodyne
``timestamp``  float64      absolute s since the epoch           Hesai
``offset_time`` uint32      ns after the header stamp            Livox
=============  ===========  ===================================  ===================

How, when the per-point times take few distinct values (a spinning lidar stamps its points by
column: an Ouster sweep has 512-2048 column times for 64k-262k points): each distinct time
gets its own exact pose (tf2's lerp + slerp per dynamic edge, composed), and each point the
pose of its time, by index (:func:`distinct`, :func:`apply_table`). The distinct values are
found without a sort: the times are binned into :data:`BUCKETS` equal bins over their span;
when no bin holds two different values, the occupied bins are the distinct times.

Otherwise (times spread continuously, or too many distinct values), the chain's pose is looked up exactly (lerp + slerp per dynamic edge, composed) at
``K`` node times spread over the cloud's time span, spaced at most :data:`NODE_NS` apart and
close enough that the rotation between two nodes is at most :data:`NODE_RAD`. Each point
then gets the pose linearly interpolated between its two nodes. Between nodes the exact
pose turns on an arc, the interpolated one on its chord: the difference is at most
``r * NODE_RAD**2 / 8`` (12.5 µm at r = 100 m), far below float32 storage. Translation is
linear between tf samples, so it is exact except within one node gap of a sample (bounded
by the change of velocity times ``NODE_NS / 4``). This costs a few passes over the points
instead of a quaternion slerp per point.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from . import compiled
from .kernels import BLOCK, Scratch

#: Node spacing limits (see the module doc).
NODE_NS = 1_000_000
NODE_RAD = 1e-3
MAX_NODES = 65_536
#: Times with at most this many distinct values get one exact pose each (:func:`distinct`).
MAX_DISTINCT = 8_192
#: Bins used to find the distinct times (a power of two above MAX_DISTINCT).
BUCKETS = 1 << 16


@dataclass(frozen=True)
class TimeField:
    """How to read per-point times: ``field`` values times ``scale`` = ns, relative to the
    header stamp or absolute."""

    field: str
    scale_ns: float
    absolute: bool
    label: str

    def offsets_ns(self, values: np.ndarray, stamp_ns: int) -> np.ndarray:
        """Per-point times as float64 ns relative to ``stamp_ns``."""
        v = values.reshape(-1)
        if self.absolute:
            # float64 seconds since the epoch: subtract in float64 seconds first (keeps ~0.2 µs)
            return (v.astype(np.float64) * (self.scale_ns / 1e9) - stamp_ns / 1e9) * 1e9
        out = v.astype(np.float64)
        if self.scale_ns != 1.0:
            out *= self.scale_ns
        return out


#: name -> (dtype kinds accepted, TimeField) for ``auto``.
CONVENTIONS: dict[str, tuple[tuple[str, ...], TimeField]] = {
    "t": (("uint32",), TimeField("t", 1.0, False, "Ouster t (uint32 ns after the header stamp)")),
    "time": (("float32",), TimeField("time", 1e9, False, "Velodyne time (float32 s relative to the header stamp)")),
    "timestamp": (("float64",), TimeField("timestamp", 1e9, True, "Hesai timestamp (float64 absolute s)")),
    "offset_time": (("uint32",), TimeField("offset_time", 1.0, False, "Livox offset_time (uint32 ns after the header stamp)")),
}
UNITS = {"ns": 1.0, "us": 1e3, "s": 1e9}
#: Field names every ROS transport keeps for deskew, whatever its channel filter says.
TIME_FIELDS = tuple(CONVENTIONS)


def time_fields(frames_cfg) -> list[str]:
    """Per-point time fields ingest's deskew reads with this ``frames:`` block (kept by a
    source whatever the ring holds); none without deskew."""
    if not frames_cfg.fixed or frames_cfg.deskew == "off":
        return []
    return [frames_cfg.deskew.field] if not isinstance(frames_cfg.deskew, str) else list(TIME_FIELDS)


def pick(channels: dict[str, np.ndarray], setting) -> Optional[TimeField]:
    """The time field to use for a cloud with these channels (None: no deskew).

    ``setting`` is ``"auto"``, ``"off"`` or a :class:`~pointflow.frames.config.DeskewConfig`."""
    if setting == "off" or setting is None:
        return None
    if setting == "auto":
        for name, (dtypes, tf) in CONVENTIONS.items():
            a = channels.get(name)
            if a is not None and a.dtype.name in dtypes and (a.ndim == 1 or a.shape[1:] == (1,)):
                return tf
        return None
    if setting.field not in channels:
        return None
    return TimeField(setting.field, UNITS[setting.unit], setting.reference == "absolute",
                     f"{setting.field} ({setting.unit}, {'absolute' if setting.reference == 'absolute' else 'after the header stamp'}, from config)")


def node_times(lo_ns: float, hi_ns: float, angle_rad: float) -> np.ndarray:
    """Node offsets (float64 ns) spanning [lo, hi]: spacing <= NODE_NS and <= NODE_RAD of turn."""
    span = max(0.0, hi_ns - lo_ns)
    k = max(2, int(math.ceil(span / NODE_NS)) + 1, int(math.ceil(angle_rad / NODE_RAD)) + 1)
    return np.linspace(lo_ns, hi_ns if span > 0 else lo_ns + 1.0, min(k, MAX_NODES))


def distinct(off: np.ndarray, lo: float, hi: float, s: Scratch) -> Optional[tuple[np.ndarray, np.ndarray]]:
    """(the distinct values of ``off`` ascending (U,), each point's index into them (N,) intp)
    when no two different values share one of :data:`BUCKETS` equal bins over [lo, hi] and
    U <= :data:`MAX_DISTINCT`; else None. ``off`` finite, lo/hi its min and max. O(N), no
    sort: bin each value, write each value into its bin (the last write wins), read them
    back; every point reads its own value only when no bin was shared."""
    n = off.shape[0]
    if not hi > lo:
        return np.array([lo]), np.zeros(n, np.intp)
    u = s.get("dk_u", (n,))
    np.subtract(off, lo, out=u)
    u *= (BUCKETS - 1) / (hi - lo)
    b = s.get("dk_bin", (n,), np.intp)
    np.copyto(b, u, casting="unsafe")  # truncation = floor (0 <= u <= BUCKETS - 1)
    table = s.get("dk_table", (BUCKETS,))
    table.fill(np.nan)
    table[b] = off
    back = np.take(table, b, out=u, mode="clip")
    if not np.array_equal(back, off):
        return None
    occ = np.flatnonzero(table == table)  # not NaN: the occupied bins, ascending
    if occ.shape[0] > MAX_DISTINCT:
        return None
    remap = s.get("dk_remap", (BUCKETS,), np.intp)
    remap[occ] = np.arange(occ.shape[0])
    idx = s.get("dk_idx", (n,), np.intp)
    np.take(remap, b, out=idx, mode="clip")
    return table[occ], idx


def _columns(pos: np.ndarray, a: int, b: int, s: Scratch) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x, y, z of points [a, b) as contiguous float64 (scratch)."""
    k = b - a
    cols = s.get("dk_cols", (3, k))
    for j in range(3):
        np.copyto(cols[j], pos[a:b, j])
    return cols[0], cols[1], cols[2]


def apply_table(pos: np.ndarray, idx: np.ndarray, R: np.ndarray, t: np.ndarray, s: Scratch) -> np.ndarray:
    """Point i with the pose (R[idx[i]], t[idx[i]]) (R (U,3,3), t (U,3)); float64 out.

    Per output coordinate r: ``t_r[idx] + sum_j R_rj[idx] p_j``: one-column ``take``s from
    U-long tables and elementwise passes, in blocks that stay in cache."""
    n = pos.shape[0]
    u = R.shape[0]
    M = np.empty((12, u))
    M[:9] = R.reshape(u, 9).T
    M[9:] = t.T
    out = np.empty((n, 3), np.float64)
    ks = compiled.load()
    if ks is not None and pos.dtype.isnative and pos.dtype.char in "fd" and pos.flags.c_contiguous and idx.dtype == np.intp:
        ks.table(pos, idx, M, out)  # one pass, the same sums in the same order (compiled.py)
        return out
    for a0 in range(0, n, BLOCK):
        b0 = min(n, a0 + BLOCK)
        k = b0 - a0
        p = _columns(pos, a0, b0, s)
        i = idx[a0:b0]
        acc = s.get("dk_acc", (k,))
        tmp = s.get("dk_tmp", (k,))
        for r in range(3):
            np.take(M[9 + r], i, out=acc, mode="clip")
            for j in range(3):
                np.take(M[3 * r + j], i, out=tmp, mode="clip")
                tmp *= p[j]
                acc += tmp
            out[a0:b0, r] = acc
    return out


def apply_nodes(pos: np.ndarray, offsets: np.ndarray, nodes: np.ndarray, R: np.ndarray, t: np.ndarray,
                s: Optional[Scratch] = None) -> np.ndarray:
    """Points at per-point ``offsets`` (ns) with poses (R (K,3,3), t (K,3)) exact at ``nodes``
    (evenly spaced), linearly interpolated between them. float64 out.

    Per output coordinate r: ``sum_j M_rj[i] p_j + f * sum_j D_rj[i] p_j`` with M the node
    poses [R | t], D their differences to the next node, i the node before each point and f
    its fraction: one-column ``take``s from K-long tables and elementwise passes, no per-point
    3x3 matrices and no BLAS (whose threads cost more than they save on (N, 3) arrays)."""
    s = s if s is not None else Scratch()
    n = pos.shape[0]
    k = nodes.shape[0]
    step = (nodes[-1] - nodes[0]) / (k - 1)
    M = np.concatenate([R.reshape(k, 9), t], axis=1).T.copy()  # (12, K): r00 r01 r02 r10 .. r22 tx ty tz
    D = np.zeros_like(M)
    D[:, :-1] = M[:, 1:] - M[:, :-1]
    out = np.empty((n, 3), np.float64)
    ks = compiled.load()
    if ks is not None and pos.dtype.isnative and pos.dtype.char in "fd" and pos.flags.c_contiguous and k >= 2:
        ks.nodes(pos, np.ascontiguousarray(offsets, np.float64), float(nodes[0]), 1.0 / step, M, D, out)
        return out
    for a0 in range(0, n, BLOCK):
        b0 = min(n, a0 + BLOCK)
        m = b0 - a0
        f = s.get("dk_f", (m,))
        np.subtract(offsets[a0:b0], nodes[0], out=f)
        f *= 1.0 / step
        np.clip(f, 0.0, k - 1, out=f)
        i = s.get("dk_i", (m,), np.intp)
        np.copyto(i, f, casting="unsafe")
        np.minimum(i, k - 2, out=i)
        f -= i  # the fraction
        p = _columns(pos, a0, b0, s)
        a = s.get("dk_acc", (m,))
        b = s.get("dk_acc2", (m,))
        tmp = s.get("dk_tmp", (m,))
        for r in range(3):
            np.take(M[9 + r], i, out=a, mode="clip")
            np.take(D[9 + r], i, out=b, mode="clip")
            for j in range(3):
                np.take(M[3 * r + j], i, out=tmp, mode="clip")
                tmp *= p[j]
                a += tmp
                np.take(D[3 * r + j], i, out=tmp, mode="clip")
                tmp *= p[j]
                b += tmp
            b *= f
            a += b
            out[a0:b0, r] = a
    return out
