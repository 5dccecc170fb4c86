"""The ingest step that puts each cloud in the fixed frame (docs/frames.md).

Ingest calls :meth:`Framer.submit` once per accepted chunk and :meth:`Framer.add_transforms`
per transforms message; both return the clouds that may go on to the ring, in order, with
their positions in the fixed frame (float64; with :attr:`Framer.lazy` a cloud that needs one
rigid transform comes as a :class:`~pointflow.frames.kernels.Placed`, its transform applied
by the ring as it writes the points). A cloud whose transform is not known yet
waits (per source, in order, at most ``tf_wait_ms`` and ``max_wait_points`` points in all);
:meth:`Framer.poll` releases or drops waiting clouds as time passes. A cloud that cannot be
placed is dropped with reason ``no_transform`` through the ``drop`` callback (ingest's
counters), so ingest's balance holds: every point is written, waiting, or dropped by reason.
"""
from __future__ import annotations

import collections
import logging
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Optional

import numpy as np

from . import compiled, deskew as dk
from .buffer import FrameError, NoTransform, TransformBuffer
from .config import FramesConfig, static_rotation
from .kernels import Placed, RigidTransform, Scratch, rigid
from .message import Transforms

#: Per-(source, reason) log lines at most this often (seconds).
LOG_EVERY_S = 5.0
Ready = tuple[Any, Any, dict]  # (chunk, float64 positions or Placed, channels)


@dataclass
class _Held:
    chunk: Any
    pos: np.ndarray
    chans: dict
    deadline_ns: int
    n: int


@dataclass
class _Source:
    frame: str = ""
    chain: str = ""
    deskew: str = "off"
    no_transform: int = 0
    clouds: int = 0
    latency_ms: Optional[float] = None
    queue: collections.deque = field(default_factory=collections.deque)
    time_field: Any = None
    time_key: Any = None
    #: (frame, buffer version, transform): this source's last cloud went through a static
    #: chain, left to the ring; the next cloud of that frame, with the buffer unchanged, takes
    #: the same transform without a lookup (:meth:`Framer.submit`'s fast path)
    fast: Any = None


class Framer:
    def __init__(self, cfg: FramesConfig, drop: Callable[[str, int], None], log: Optional[logging.Logger] = None,
                 spans=None, clock: Callable[[], int] = time.monotonic_ns):
        assert cfg.fixed, "a Framer needs frames.fixed"
        self.cfg = cfg
        self.fixed = cfg.fixed
        self.buffer = TransformBuffer(int(cfg.history_s * 1e9))
        for s in cfg.static:
            self.buffer.set_transform(s.parent, s.child, 0, s.translation, static_rotation(s), static=True)
        self.wait_ns = int(cfg.tf_wait_ms * 1e6)
        self.drop = drop
        self.log = log or logging.getLogger("pointflow.frames")
        self.spans = spans
        self.clock = clock
        self.sources: dict[str, _Source] = {}
        self.transforms_in = 0
        self.transforms_rejected: collections.Counter[str] = collections.Counter()
        self.waiting_points = 0
        self.transform_ns = 0
        self._logged: dict[tuple[str, str], float] = {}
        self._static_cache: dict[str, tuple[int, Any]] = {}
        #: intermediates of the point loops, kept between clouds (kernels.py)
        self.scratch = Scratch()
        #: True: a cloud that needs one rigid transform comes back as a :class:`Placed` (its
        #: positions as sent and the transform), which the ring applies as it writes them
        #: (ingest sets this unless it needs the placed positions itself: recording, thinning)
        self.lazy = False
        compiled.load()  # numba's import and the cached machine code: now, not at the first cloud

    # ------------------------------------------------------------------ transforms
    def add_transforms(self, batch: Transforms) -> list[Ready]:
        """Take a batch of transforms (refused ones counted and logged); release what waited on them."""
        for tf in batch.transforms:
            try:
                self.buffer.set_transform(tf.parent, tf.child, tf.stamp_ns, tf.translation, tf.rotation, tf.static)
                self.transforms_in += 1
            except FrameError as exc:
                self.transforms_rejected[exc.reason] += 1
                self._warn(batch.source_id or "?", exc.reason, f"transform refused [{exc.reason}]: {exc}")
        return self.poll() if self.waiting_points or any(s.queue for s in self.sources.values()) else []

    # ------------------------------------------------------------------ clouds
    def submit(self, chunk, pos: np.ndarray, chans: dict) -> list[Ready]:
        """One accepted cloud: placed now, held until its transform arrives, or dropped."""
        st = self.sources.get(chunk.source_id)
        if st is None:
            st = self.sources[chunk.source_id] = _Source()
        st.clouds += 1
        f = st.fast
        if f is not None and f[0] == chunk.frame_id and f[1] == self.buffer.version and not st.queue:
            # a static chain, nothing changed: the per-cloud work is this check (~0.3 us)
            if self.spans is not None and chunk.trace_id:
                self.spans.record(chunk.trace_id, "transform", chunk.t_recv_ns or time.monotonic_ns(),
                                  time.monotonic_ns(), int(pos.shape[0]))
            return [(chunk, Placed(pos, f[2], True), chans)]
        if st.queue:  # an earlier cloud of this source waits: keep the order
            return self._hold(st, chunk, pos, chans) + self.poll()
        try:
            return [(chunk, self._place(st, chunk, pos), chans)]
        except FrameError as exc:
            if getattr(exc, "retry", False) and self.wait_ns > 0:
                return self._hold(st, chunk, pos, chans)
            self._drop(st, chunk, exc)
            return []

    def _hold(self, st: _Source, chunk, pos, chans) -> list[Ready]:
        n = int(pos.shape[0])
        st.queue.append(_Held(chunk, pos, chans, self.clock() + self.wait_ns, n))
        self.waiting_points += n
        out: list[Ready] = []
        while self.waiting_points > self.cfg.max_wait_points:
            # bounded: the oldest waiting cloud gets one more try, then gives up
            victim = min((s for s in self.sources.values() if s.queue), key=lambda s: s.queue[0].deadline_ns)
            h = victim.queue.popleft()
            self.waiting_points -= h.n
            try:
                out.append((h.chunk, self._place(victim, h.chunk, h.pos), h.chans))
            except FrameError as exc:
                self._drop(victim, h.chunk, exc, why=f"the wait buffer is full ({self.cfg.max_wait_points:,} points)")
        return out

    def poll(self, final: bool = False) -> list[Ready]:
        """Release waiting clouds whose transforms have arrived (in order per source); drop
        those whose wait is over (``final``: all that cannot be placed now)."""
        out: list[Ready] = []
        if not self.waiting_points:
            return out
        now = self.clock()
        for st in self.sources.values():
            while st.queue:
                h = st.queue[0]
                try:
                    pos = self._place(st, h.chunk, h.pos)
                except FrameError as exc:
                    if getattr(exc, "retry", False) and not final and now < h.deadline_ns:
                        break
                    st.queue.popleft()
                    self.waiting_points -= h.n
                    self._drop(st, h.chunk, exc, why=f"after waiting {(now - (h.deadline_ns - self.wait_ns)) / 1e6:.0f} ms")
                    continue
                st.queue.popleft()
                self.waiting_points -= h.n
                out.append((h.chunk, pos, h.chans))
        return out

    @property
    def waiting(self) -> bool:
        return self.waiting_points > 0

    # ------------------------------------------------------------------ placing
    def _place(self, st: _Source, chunk, pos: np.ndarray) -> np.ndarray:
        """Positions in the fixed frame; FrameError (NoTransform when waiting may help)."""
        try:
            return self._place_unchecked(st, chunk, pos)
        except FrameError:
            raise
        except Exception as exc:  # noqa: BLE001 - a bad time field or a bug: drop the cloud (counted), keep going
            raise FrameError("transform_error", f"placing the cloud failed: {type(exc).__name__}: {exc}") from None

    def _place_unchecked(self, st: _Source, chunk, pos: np.ndarray) -> np.ndarray:
        t0 = time.monotonic_ns()
        frame = chunk.frame_id or ""
        if frame != st.frame or not st.chain:
            st.frame = frame
            st.chain = self.buffer.chain_text(self.fixed, frame) if frame else "(no frame: as sent)"
        if not frame or frame == self.fixed:
            out = pos  # already in the fixed frame (or carries no frame: taken as sent)
            if not frame:
                self._warn(chunk.source_id, "no_frame", f"source {chunk.source_id!r} sends clouds without a frame id; "
                           f"they are taken as already in {self.fixed!r} (set sources[].frame_id)", level=logging.INFO)
        else:
            stamp = int(chunk.stamp_ns)
            static = self._static_chain(frame)
            tf = self._time_field(st, chunk) if static is None else None
            if static is not None:  # a chain of static edges only: one cached transform, nothing to deskew
                out = Placed(pos, static, True) if self.lazy else static.world(pos)
                if st.chain.startswith("("):
                    st.chain = self.buffer.chain_text(self.fixed, frame)
                if self.lazy and st.latency_ms is None:
                    st.fast = (frame, self.buffer.version, static)
            elif tf is not None and stamp:
                out = self._deskew(chunk, pos, tf, frame, stamp)
            else:
                R, t = self.buffer.lookup(self.fixed, frame, stamp)
                out = Placed(pos, RigidTransform(R, t, self.scratch), False) if self.lazy else rigid(pos, R, t, self.scratch)
            if static is None or st.latency_ms is not None:
                newest = self.buffer.newest_of_chain(self.fixed, frame)
                st.latency_ms = round((newest - stamp) / 1e6, 3) if newest is not None and stamp else None
                st.chain = self.buffer.chain_text(self.fixed, frame)
        t1 = time.monotonic_ns()
        self.transform_ns += t1 - t0
        if self.spans is not None and chunk.trace_id:
            self.spans.record(chunk.trace_id, "transform", chunk.t_recv_ns or t0, t1, int(pos.shape[0]))
        return out

    def _static_chain(self, frame: str) -> Optional[RigidTransform]:
        """fixed <- frame when every edge of the chain is static (cached until the buffer
        changes: the same object for every cloud); None for a chain with a dynamic edge.
        Raises NoTransform."""
        hit = self._static_cache.get(frame)
        if hit is not None and hit[0] == self.buffer.version:
            return hit[1]
        value = None
        if not self.buffer.dynamic_edges(self.fixed, frame):
            value = RigidTransform(*self.buffer.lookup(self.fixed, frame, 0), self.scratch)
        self._static_cache[frame] = (self.buffer.version, value)
        return value

    def _deskew(self, chunk, pos: np.ndarray, tf: dk.TimeField, frame: str, stamp: int) -> np.ndarray:
        off = tf.offsets_ns(chunk.channels[tf.field], stamp)
        if off.shape[0] != pos.shape[0]:
            raise ValueError(f"time field {tf.field!r} has {off.shape[0]} values for {pos.shape[0]} points")
        if off.shape[0] == 0:
            R, t = self.buffer.lookup(self.fixed, frame, stamp)
            return rigid(pos, R, t, self.scratch)
        lo, hi = float(off.min()), float(off.max())
        if not (np.isfinite(lo) and np.isfinite(hi)):
            off = np.nan_to_num(off, nan=0.0, posinf=0.0, neginf=0.0)
            lo, hi = float(off.min()), float(off.max())
        d = dk.distinct(off, lo, hi, self.scratch)
        if d is not None:  # few distinct times (a column per time): one exact pose each
            values, idx = d
            R, t = self.buffer.lookup_many(self.fixed, frame, stamp + np.rint(values).astype(np.int64))
            return dk.apply_table(pos, idx, R, t, self.scratch)
        ends = np.array([stamp + int(np.floor(lo)), stamp + int(np.ceil(hi))], dtype=np.int64)
        Re, _ = self.buffer.lookup_many(self.fixed, frame, ends)
        c = (np.trace(Re[0].T @ Re[1]) - 1.0) / 2.0
        angle = float(np.arccos(np.clip(c, -1.0, 1.0)))
        nodes = dk.node_times(lo, hi, angle)
        times = stamp + np.rint(nodes).astype(np.int64)
        R, t = self.buffer.lookup_many(self.fixed, frame, times)
        return dk.apply_nodes(pos, off, (times - stamp).astype(np.float64), R, t, self.scratch)

    def _time_field(self, st: _Source, chunk) -> Optional[dk.TimeField]:
        if self.cfg.deskew == "off":
            return None
        ch = chunk.channels
        key = tuple((k, v.dtype.str) for k, v in ch.items())
        if key != st.time_key:
            st.time_key = key
            st.time_field = dk.pick(ch, self.cfg.deskew)
            label = st.time_field.label if st.time_field is not None else "off"
            if label != st.deskew:
                st.deskew = label
                why = "" if st.time_field is not None or self.cfg.deskew == "off" else " (no per-point time field found)"
                self.log.info("frames: source %r: deskew %s%s", chunk.source_id, label, why)
        return st.time_field

    # ------------------------------------------------------------------ dropping
    def _drop(self, st: _Source, chunk, exc: FrameError, why: str = "") -> None:
        n = int(chunk.n)
        reason = "tf_wait_overflow" if why.startswith("the wait buffer") else exc.reason
        if reason == "no_transform":
            st.no_transform += n
        self.drop(reason, n)
        self._warn(chunk.source_id, reason,
                   f"dropped cloud of {n} points from {chunk.source_id!r} [{reason}]: frame {chunk.frame_id!r} "
                   f"at {chunk.stamp_ns / 1e9:.6f} s not placed in {self.fixed!r}"
                   f"{' ' + why if why else ''}: {exc}")

    def _warn(self, source: str, reason: str, message: str, level: int = logging.WARNING) -> None:
        now = time.monotonic()
        key = (source, reason)
        if now - self._logged.get(key, -1e9) >= LOG_EVERY_S:
            self._logged[key] = now
            self.log.log(level, "frames: %s", message)

    # ------------------------------------------------------------------ stats
    def stats(self) -> dict[str, Any]:
        return {
            "fixed": self.fixed,
            "transforms_in": self.transforms_in,
            "transforms_rejected": dict(self.transforms_rejected),
            "edges": len(self.buffer.edges),
            "waiting_points": self.waiting_points,
            "transform_ms": round(self.transform_ns / 1e6, 3),
            "sources": {k: {"frame": s.frame or None, "chain": s.chain, "deskew": s.deskew,
                            "tf_latency_ms": s.latency_ms, "no_transform": s.no_transform, "clouds": s.clouds,
                            "waiting_clouds": len(s.queue)}
                        for k, s in self.sources.items()},
        }
