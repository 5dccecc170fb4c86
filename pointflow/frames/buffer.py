"""A transform buffer like tf2's: parent -> child edges, static or time-stamped with a
bounded history, composed into "target <- source at time t".

Each dynamic edge keeps its samples sorted by stamp and answers a time between two of them
the way tf2 does: translation linearly, rotation by slerp. A time outside an edge's
history (before its first sample or after its newest) is never extrapolated: the lookup
raises :class:`NoTransform` saying what the buffer holds. The tree is checked as edges
arrive: a second parent for a child or an edge that would close a loop is refused with a
:class:`FrameError` (reasons ``tf_two_parents``, ``tf_loop``), so a lookup can never walk
in a circle. Everything is float64; lookups are vectorised over many times (deskew).
"""
from __future__ import annotations

import bisect
from typing import Optional, Sequence

import numpy as np

from ..errors import Error
from .rotation import normalise, slerp, to_matrix

#: Default history kept per dynamic edge (tf2's default cache time).
HISTORY_NS = 10_000_000_000
#: Hard cap on samples per edge, whatever the history (a 1 kHz publisher for 10 s).
MAX_SAMPLES = 20_000


class FrameError(Error, ValueError):
    """A transform or lookup was refused; ``reason`` is the short key counted in stats."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


class NoTransform(FrameError):
    """No transform for (frame, time): unknown frame, not connected, or out of history."""

    def __init__(self, message: str, retry: bool = False):
        super().__init__("no_transform", message)
        #: True when waiting may help (the time is after the newest sample of an edge).
        self.retry = retry


class _Edge:
    """One parent -> child edge: a static transform or a sorted, bounded sample history."""

    __slots__ = ("parent", "static", "stamps", "values", "_arr")

    def __init__(self, parent: str, static: bool):
        self.parent = parent
        self.static = static
        self.stamps: list[int] = []
        self.values: list[tuple[float, ...]] = []  # tx ty tz qx qy qz qw
        self._arr: Optional[tuple[np.ndarray, np.ndarray, np.ndarray]] = None

    def add(self, stamp: int, value: tuple[float, ...], history_ns: int) -> None:
        if self.static:
            self.stamps, self.values = [stamp], [value]
        elif not self.stamps or stamp > self.stamps[-1]:
            self.stamps.append(stamp)
            self.values.append(value)
        else:
            i = bisect.bisect_left(self.stamps, stamp)
            if i < len(self.stamps) and self.stamps[i] == stamp:
                self.values[i] = value
            else:
                self.stamps.insert(i, stamp)
                self.values.insert(i, value)
        if not self.static:
            cut = bisect.bisect_left(self.stamps, self.stamps[-1] - history_ns)
            cut = max(cut, len(self.stamps) - MAX_SAMPLES)
            if cut > 0:
                del self.stamps[:cut], self.values[:cut]
        self._arr = None

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self._arr is None:
            v = np.array(self.values, dtype=np.float64).reshape(-1, 7)
            self._arr = (np.array(self.stamps, dtype=np.int64), v[:, :3], normalise(v[:, 3:]))
        return self._arr

    def span(self) -> str:
        if self.static:
            return "static"
        return f"{self.stamps[0] / 1e9:.3f}..{self.stamps[-1] / 1e9:.3f} s, {len(self.stamps)} samples"


class TransformBuffer:
    """Static and dynamic transforms; ``lookup(target, source, t)`` composes the chain."""

    def __init__(self, history_ns: int = HISTORY_NS):
        self.history_ns = int(history_ns)
        self.edges: dict[str, _Edge] = {}  # child -> edge to its parent
        self.newest_ns = 0
        self.version = 0  # bumped on every accepted transform (waiting clouds retry then)

    # ------------------------------------------------------------------ input
    def set_transform(self, parent: str, child: str, stamp_ns: int, translation: Sequence[float],
                      rotation: Sequence[float], static: bool = False) -> None:
        """Add one parent -> child transform (rotation as an (x, y, z, w) quaternion).

        Raises :class:`FrameError` for a second parent of ``child``, a loop, an empty or
        equal frame pair, a non-finite value or a zero quaternion; the buffer is unchanged."""
        if not parent or not child or not isinstance(parent, str) or not isinstance(child, str):
            raise FrameError("tf_bad", f"transform needs two frame names, got parent {parent!r}, child {child!r}")
        if parent == child:
            raise FrameError("tf_loop", f"transform from {parent!r} to itself")
        value = tuple(float(v) for v in translation) + tuple(float(v) for v in rotation)
        if len(value) != 7 or not all(np.isfinite(value)):
            raise FrameError("tf_bad", f"transform {parent} -> {child}: translation must be 3 and rotation 4 finite numbers")
        qn = float(np.linalg.norm(value[3:]))
        if qn < 1e-6:
            raise FrameError("tf_bad", f"transform {parent} -> {child}: rotation quaternion has zero length")
        edge = self.edges.get(child)
        if edge is not None and edge.parent != parent:
            raise FrameError("tf_two_parents", f"frame {child!r} already has parent {edge.parent!r}; "
                             f"a transform from {parent!r} to it is refused (a frame has one parent)")
        if edge is None:
            # a loop: child is already an ancestor of parent
            f, seen = parent, 0
            while f in self.edges and seen <= len(self.edges):
                f = self.edges[f].parent
                seen += 1
                if f == child:
                    raise FrameError("tf_loop", f"transform {parent} -> {child} would close a loop in the "
                                     f"transform tree ({child!r} is already above {parent!r}: {self.path_up(parent)})")
            edge = self.edges[child] = _Edge(parent, static)
        elif edge.static != static:
            kind = "static" if edge.static else "dynamic"
            raise FrameError("tf_two_parents", f"frame {child!r} has a {kind} transform from {parent!r}; "
                             f"a {'static' if static else 'dynamic'} one for the same edge is refused")
        edge.add(int(stamp_ns), value, self.history_ns)
        if not static and stamp_ns > self.newest_ns:
            self.newest_ns = int(stamp_ns)
        self.version += 1

    # ------------------------------------------------------------------ chain
    def path_up(self, frame: str) -> str:
        return " -> ".join(self._ancestors(frame))

    def _ancestors(self, frame: str) -> list[str]:
        out = [frame]
        while frame in self.edges and len(out) <= len(self.edges) + 1:
            frame = self.edges[frame].parent
            out.append(frame)
        return out

    def chain(self, target: str, source: str) -> tuple[list[str], list[str]]:
        """(frames from source up to the common ancestor, frames from target up to it)."""
        up_s = self._ancestors(source)
        up_t = self._ancestors(target)
        common = next((f for f in up_s if f in set(up_t)), None)
        if common is None:
            known = set(self.edges) | {e.parent for e in self.edges.values()}
            missing = [f for f in (source, target) if f not in known]
            what = (f"unknown frame {missing[0]!r}" if missing else f"frame {source!r} is not connected to {target!r}")
            raise NoTransform(f"{what}: " + self.describe(), retry=True)
        return up_s[:up_s.index(common) + 1], up_t[:up_t.index(common) + 1]

    def chain_text(self, target: str, source: str) -> str:
        """``odom <- base_link <- lidar_top`` (``~`` marks a dynamic edge)."""
        try:
            s, t = self.chain(target, source)
        except NoTransform:
            return "(not connected)"
        parts = list(t)  # target ... common
        for f in reversed(s[:-1]):
            parts.append(f)
        return " <- ".join(parts)

    def dynamic_edges(self, target: str, source: str) -> list[str]:
        s, t = self.chain(target, source)
        return [c for c in s[:-1] + t[:-1] if not self.edges[c].static]

    # ------------------------------------------------------------------ lookup
    def _edge_at(self, child: str, times: Optional[np.ndarray]):
        """(R, t) of parent <- child at ``times`` ((M,3,3),(M,3)) or static ((3,3),(3,))."""
        e = self.edges[child]
        st, tr, q = e.arrays()
        if e.static or times is None:
            if times is None and not e.static:  # time 0: the newest sample (tf2's "latest")
                return to_matrix(q[-1]), tr[-1]
            return to_matrix(q[0]), tr[0]
        lo, hi = int(times.min()), int(times.max())
        if lo < st[0] or hi > st[-1]:
            when = lo if lo < st[0] else hi
            raise NoTransform(f"no transform {e.parent} -> {child} at {when / 1e9:.6f} s "
                              f"(history of that edge: {e.span()}); not extrapolated",
                              retry=hi > st[-1] and lo >= st[0])
        i = np.searchsorted(st, times, side="right") - 1
        i = np.clip(i, 0, len(st) - 2) if len(st) > 1 else np.zeros_like(i)
        if len(st) == 1:
            return to_matrix(np.broadcast_to(q[0], times.shape + (4,))), np.broadcast_to(tr[0], times.shape + (3,))
        t0, t1 = st[i], st[i + 1]
        a = (times - t0).astype(np.float64) / (t1 - t0).astype(np.float64)
        trans = tr[i] + a[:, None] * (tr[i + 1] - tr[i])
        rot = to_matrix(slerp(q[i], q[i + 1], a))
        return rot, trans

    def lookup_many(self, target: str, source: str, times: Optional[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """target <- source at each of ``times`` (int64 ns, (M,)): R (M,3,3), t (M,3);
        ``times=None`` = the newest transforms. Raises :class:`NoTransform`."""
        if target == source:
            m = 1 if times is None else times.shape[0]
            return np.broadcast_to(np.eye(3), (m, 3, 3)).copy(), np.zeros((m, 3))
        up_s, up_t = self.chain(target, source)
        R_s, t_s = self._compose(up_s, times)
        R_t, t_t = self._compose(up_t, times)
        # target <- common = inverse(common <- target)
        R_ti = np.swapaxes(R_t, -1, -2)
        R = R_ti @ R_s
        t = np.einsum("...ij,...j->...i", R_ti, t_s - t_t)
        m = 1 if times is None else times.shape[0]
        return np.broadcast_to(R, (m, 3, 3)), np.broadcast_to(t, (m, 3))

    def _compose(self, path: list[str], times: Optional[np.ndarray]):
        """common <- path[0] along the path (path[-1] is the common ancestor)."""
        R = np.eye(3)
        t = np.zeros(3)
        for child in reversed(path[:-1]):  # from the top down: common <- ... <- child
            Re, te = self._edge_at(child, times)
            t = np.einsum("...ij,...j->...i", R, te) + t
            R = R @ Re
        return R, t

    def lookup(self, target: str, source: str, stamp_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """target <- source at one time (0 = newest): R (3,3), t (3,)."""
        times = None if not stamp_ns else np.array([stamp_ns], dtype=np.int64)
        R, t = self.lookup_many(target, source, times)
        return np.ascontiguousarray(R[0]), np.ascontiguousarray(t[0])

    def newest_of_chain(self, target: str, source: str) -> Optional[int]:
        """The oldest of the newest stamps of the chain's dynamic edges (None: static chain)."""
        try:
            dyn = self.dynamic_edges(target, source)
        except (NoTransform, KeyError):
            return None
        return min((self.edges[c].stamps[-1] for c in dyn), default=None)

    def describe(self) -> str:
        """What the buffer holds, one clause per edge (for log lines)."""
        if not self.edges:
            return "the transform buffer is empty"
        return "the buffer holds " + "; ".join(f"{e.parent} -> {c} ({e.span()})" for c, e in sorted(self.edges.items()))
