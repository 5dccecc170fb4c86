"""The ingest stage: ZeroMQ chunks in, validated SoA points into the shared-memory ring.

One loop, one process: drain the PULL socket (bounded by the ZeroMQ receive high-water
mark), decode each message (binary wire format, or a one-frame JSON chunk), validate,
drop non-finite points, convert to the ring's channels, resolve the importance field,
coalesce small chunks into batches (a bounded queue that drops its oldest batch when full)
and push the batches into the ring. Nothing a sender does can crash it: every defect is a
:class:`ChunkError` whose reason is counted and logged (rate-limited).

Accounting (exact, see docs/ingest.md)::

    messages_in = chunks_accepted + transform_messages + sum(rejected[reason])   (messages)
    points_in   = points_out + sum(drops[reason])                  (points of accepted chunks)

(the second once quiet: points still queued, or waiting for transforms in the frames step,
are in neither term yet; the frames step drops with ``no_transform``, see docs/frames.md)

where ``points_out`` is what the ring stored and ``drops`` holds ``non_finite``,
``out_of_range`` (finite, but too far from the ring's origin to be stored as a float32
offset: see ``pointflow.ring.ring.MAX_OFFSET``), ``queue_overflow``, ``thinned`` and
``ring_full`` (incoming points the ring did not
keep: refused under ``drop_newest``, or evicted by more important points of the same push). Points the ring evicted to make room are ``extra["ring_evicted"]``; so
the ring's own ``dropped_points`` equals ``ring_evicted + drops["ring_full"]`` and its
``total_written`` equals ``points_out``.
"""
from __future__ import annotations

import collections
import json
import dataclasses
import logging
import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
import zmq

from .. import wire
from ..arrays import rgb_u8
from ..chunk import ChunkError, PointChunk
from ..frames import message as transforms
from ..frames.kernels import Placed
from ..ring.config import IMPORTANCE_SLOT, importance_values
from ..stage.kinds import StageKind, register_stage_kind
from ..stage.context import RateLimitedLog, recv_frames, take_messages  # noqa: F401 - recv_frames: bench/ab_ingest.py
from .jsonchunk import parse_json_chunk

#: Per-reason log lines at most this often (seconds).
#: The ring's only writer: starts after what it sends to (render, cadence, the recorder),
#: stops after the sources and before the cadence, so it drains what they sent.
KIND = register_stage_kind(StageKind(
    name="ingest", main="pointflow.ingest.process:main", prepare="pointflow.ingest.process:prepare",
    start_order=30, stop_wave=1, standby=True,
    counters=("messages_in", "chunks_accepted", "transform_messages", "rejected_messages", "ring_evicted",
              "ring_pushes",
              # its copies for the recording (record/tap.py, docs/record.md)
              "record_offered", "record_sent", "record_dropped", "record_messages_sent",
              "record_transforms_sent", "record_transforms_dropped",
              # points a killed ingest wrote into the ring but never reported (reconciled from
              # the ring's own counter, runtime/accounting.py)
              "unreported_written"),
    accounting="pointflow.ingest.accounting:ingest_identities"))

#: On stop, drain the ingest socket until it is quiet this long, for at most STOP_GRACE_S.
STOP_QUIET_S = 0.15
STOP_GRACE_S = 1.5
_min, _max = np.minimum.reduce, np.maximum.reduce
_INF = float("inf")
#: Adaptive thinning steps: (ring fill fraction, keep every k-th point).
THINNING = ((0.985, 4), (0.95, 2))


@dataclass
class _Batch:
    """Chunks queued for one ring push (converted arrays, not yet concatenated)."""

    positions: list[np.ndarray] = field(default_factory=list)
    channels: list[dict[str, np.ndarray]] = field(default_factory=list)
    traces: list[int] = field(default_factory=list)
    n: int = 0
    #: min and max over every coordinate of the batch (passed to ``PointRing.push``)
    lo: float = float("inf")
    hi: float = float("-inf")
    #: False when a chunk was queued unchecked (small chunks): flush() drops its non-finite
    #: points and takes the min and max over the whole batch
    checked: bool = True
    #: Holds one big chunk: pushed as is, nothing added to it.
    solo: bool = False
    #: With a recording: each chunk's points and metadata, offered to the recorder once pushed.
    records: list[PointChunk] = field(default_factory=list)
    #: The rigid transform the ring applies to every point of the batch as it writes them
    #: (frames step, static chain or a big cloud; positions are then as sent and lo/hi bound
    #: the placed coordinates), or None: positions already placed.
    xf: Any = None


class Ingestor:
    """Decode → validate → convert → coalesce → push, with exact counters.

    Independent of the process loop so tests and benchmarks can drive it directly."""

    def __init__(self, ring, *, max_chunk_points: int = 5_000_000, coalesce_points: int = 20_000,
                 queue_max_batches: int = 64, adaptive_thinning: bool = False,
                 importance_field: str | None = None, counters=None, spans=None,
                 log: logging.Logger | None = None, frames=None, record=None):
        from ..stage.context import StageCounters

        self.ring = ring
        self.max_chunk_points = max_chunk_points
        self.coalesce_points = coalesce_points
        self.queue_max_batches = queue_max_batches
        self.adaptive_thinning = adaptive_thinning
        self.counters = counters if counters is not None else StageCounters()
        self.spans = spans
        self.log = log or logging.getLogger("pointflow.ingest")
        self._warn = RateLimitedLog(self.log)
        self.specs = {c.name: c for c in ring.channels}
        self._dtypes = {c.name: np.dtype(c.dtype) for c in ring.channels}  # not rebuilt per chunk
        # A config that ranks points has a ring with its own importance array
        # (ring/config.py, importance_slot); ingest fills it from the configured field.
        self._imp_key = IMPORTANCE_SLOT if ring.importance_field == IMPORTANCE_SLOT and IMPORTANCE_SLOT not in self.specs \
            else None
        self.importance_source = importance_field
        self.queue: collections.deque[_Batch] = collections.deque()
        self.rejected: collections.Counter[str] = collections.Counter()
        self.messages_in = 0
        self.chunks_accepted = 0
        self.ring_evicted = 0
        self.pushes = 0
        self._ring_written_seen = 0
        #: A :class:`pointflow.record.tap.RecordTap` when the pipeline records (docs/record.md).
        self.record = record
        self._fill = 0.0
        self._fill_checked = 0.0
        #: The frames step (docs/frames.md): None = points as sent (``frames.fixed`` null).
        self.framer = None
        self.transform_messages = 0
        if frames is not None and frames.fixed:
            from ..frames.framer import Framer
            self.framer = Framer(frames, self.counters.drop, self.log, spans)
            # rigid transforms applied by the ring as it writes (one pass over the points, no
            # float64 copy), unless the placed positions are needed here first
            self.framer.lazy = record is None and not adaptive_thinning

    # ------------------------------------------------------------------ receive
    def receive(self, frames: Sequence[Any]) -> bool:
        """Take one ZeroMQ message; False when it was rejected (counted)."""
        self.messages_in += 1
        t0 = time.monotonic_ns()
        try:
            if len(frames) == 1:
                buf = frames[0].buffer if hasattr(frames[0], "buffer") else frames[0]
                raw = bytes(buf)
                if transforms.SCHEMA_BYTES in raw:  # maybe pointflow.transforms/1 (docs/frames.md)
                    return self.add_json(raw, t0)
                chunk = parse_json_chunk(raw, self.max_chunk_points)
                return self.add_chunk(chunk, t0)
            # wire.decode already checks counts, shapes, dtypes and the size limit
            chunk = wire.decode(frames, self.max_chunk_points)
        except ChunkError as exc:
            self.reject(exc.reason, str(exc))
            return False
        except Exception as exc:  # noqa: BLE001 - a decoder bug must not kill the stage
            self.reject("decode_error", f"{type(exc).__name__}: {exc}")
            return False
        return self.add_chunk(chunk, t0, validated=True)

    def reject(self, reason: str, message: str) -> None:
        self.rejected[reason] += 1
        self._warn(reason, message)

    #: ``render.color_by`` when it is a channel of the data: a source whose points lack it is
    #: named once (config.py refuses it at load where the sources' channels are known).
    color_by: str | None = None
    #: ``color_by`` is the default (intensity), not the user's choice: an xyz-only source is
    #: then said at info, not warned of (every Pipeline.send of bare xyz warned)
    color_by_default: bool = False

    def _colour_missing(self, chunk: PointChunk) -> None:
        warned = self.__dict__.setdefault("_colour_warned", set())
        if chunk.source_id in warned:
            return
        warned.add(chunk.source_id)
        have = ", ".join(sorted(chunk.channels)) or "none"
        self.log.log(logging.INFO if self.color_by_default else logging.WARNING,
                     "render.color_by: the points of source %r have no channel %r (channels that arrive: %s); "
                     "they are drawn in the single colour render.color", chunk.source_id, self.color_by, have)

    def add_chunk(self, chunk: PointChunk, t0_ns: int | None = None, validated: bool = False) -> bool:
        """Validate and convert a decoded chunk, then queue it. False when rejected."""
        t0 = t0_ns or time.monotonic_ns()
        chunk.t_recv_ns = chunk.t_recv_ns or t0
        try:
            if not validated:
                chunk.validate(self.max_chunk_points)
            pos, chans = self._convert(chunk)
        except ChunkError as exc:
            self.reject(exc.reason, f"source {chunk.source_id!r} seq {chunk.seq}: {exc}")
            return False
        self.chunks_accepted += 1
        if self.color_by is not None and self.color_by not in chunk.channels:
            self._colour_missing(chunk)
        self.counters.points_in += chunk.positions.shape[0]  # not chunk.n: a property, ~0.2 us
        if self.framer is not None:  # into the fixed frame; may wait for transforms (docs/frames.md)
            for c, p, ch in self.framer.submit(chunk, pos, chans):
                self._admit(c, p, ch, t0)
            return True
        return self._admit(chunk, pos, chans, t0)

    def add_json(self, raw: bytes, t0: int) -> bool:
        """A one-frame JSON message that may be a transforms message or a JSON chunk."""
        try:
            obj = json.loads(raw)
        except ValueError:
            obj = None
        if transforms.is_transforms(obj):
            return self.add_transforms(obj)
        return self.add_chunk(parse_json_chunk(obj if isinstance(obj, dict) else raw, self.max_chunk_points), t0)

    def add_transforms(self, obj: dict) -> bool:
        """A ``pointflow.transforms/1`` message: into the frames step (ignored, but counted,
        when ``frames.fixed`` is null). False when it was malformed (rejected, counted)."""
        try:
            batch = transforms.decode(obj)
        except transforms.TransformMessageError as exc:
            self.reject(exc.reason, f"transforms message: {exc}")
            return False
        self.transform_messages += 1
        if self.framer is not None:
            if self.record is not None:  # /tf and /tf_static in the recording (docs/record.md)
                self.record.offer_transforms(batch)
            for c, p, ch in self.framer.add_transforms(batch):
                self._admit(c, p, ch)
        return True

    def _admit(self, chunk: PointChunk, pos: np.ndarray, chans: dict[str, np.ndarray], t0: int | None = None) -> bool:
        """Non-finite points, thinning, then the push queue (positions in their final frame)."""
        t0 = t0 or time.monotonic_ns()
        xf = None
        if type(pos) is Placed:  # the frames step left the rigid transform to the ring
            if pos.shared or 2 * pos.src.shape[0] >= self.coalesce_points:
                pos, xf = pos.src, pos.xf
            else:  # a small cloud with a transform of its own: placed now, so it coalesces
                pos = pos.xf.world(pos.src)
        n = pos.shape[0]
        if n and 2 * n < self.coalesce_points and not self.adaptive_thinning and self.record is None:
            # a small chunk goes into a coalesced batch: flush() finds its non-finite points
            # with one min/max over the whole batch instead of two reductions per chunk (not when
            # recording: the recorder's copy is taken at enqueue and must hold only finite points)
            if self.spans is not None:
                self.spans.record(chunk.trace_id, "ingest_packed", chunk.t_recv_ns or t0, time.monotonic_ns(), n)
            self._enqueue(pos, chans, chunk.trace_id, None, None, xf=xf)
            return True
        pos, chans, lo, hi = self._finite(pos, chans)
        if xf is not None and pos.shape[0]:
            # bounds of the placed coordinates; a finite point stays finite when placed (only a
            # coordinate near 1e308 could overflow, and the ring's range rule refuses that one)
            lo, hi = xf.bounds(lo, hi)
        if self.adaptive_thinning and pos.shape[0]:
            k = self._thin_step()
            if k > 1:
                m = pos.shape[0]
                pos = pos[::k]
                chans = {c: v[::k] for c, v in chans.items()}
                self.counters.drop("thinned", m - pos.shape[0])
        if self.spans is not None:
            self.spans.record(chunk.trace_id, "ingest_packed", chunk.t_recv_ns or t0, time.monotonic_ns(), pos.shape[0])
        if pos.shape[0]:
            rec = None
            if self.record is not None:  # what goes into the ring, with the chunk's metadata
                rec = dataclasses.replace(chunk, positions=pos, channels=self.record.chans(chans),
                                          stamp_ns=chunk.stamp_ns or time.time_ns(),
                                          frame_id=self.framer.fixed if self.framer is not None else chunk.frame_id)
            self._enqueue(pos, chans, chunk.trace_id, lo, hi, rec, xf)  # thinning keeps a subset: still bounds
        return True

    def _finite(self, pos: np.ndarray, chans: dict[str, np.ndarray]) -> tuple[np.ndarray, dict[str, np.ndarray], float, float]:
        """Drop (and count) the points with a non-finite coordinate; also returns the min and
        max over every coordinate kept, which the ring reuses for its range rule instead of
        scanning the points again."""
        n = pos.shape[0]
        if not n:
            return pos, chans, 0.0, 0.0
        # fast path: the min and max of all values (NaN or inf there iff some value is not
        # finite; the per-row test is ~10x slower and only needed then)
        lo, hi = float(_min(pos, axis=None)), float(_max(pos, axis=None))
        if not (-_INF < lo and hi < _INF):  # also False for NaN
            fin = np.isfinite(pos).all(axis=1)
            bad = n - int(np.count_nonzero(fin))
            if bad:
                self.counters.drop("non_finite", bad)
                pos = pos[fin]
                chans = {k: v[fin] for k, v in chans.items()}
            if pos.shape[0]:
                lo, hi = float(_min(pos, axis=None)), float(_max(pos, axis=None))
        return pos, chans, lo, hi

    def _convert(self, chunk: PointChunk) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Only the ring's channels, in the ring's dtypes; importance resolved."""
        out: dict[str, np.ndarray] = {}
        n = chunk.positions.shape[0]
        dtypes = self._dtypes
        for name, spec in self.specs.items():
            arr = chunk.channels.get(name)
            if arr is None:
                continue
            if spec.width == 1 and arr.ndim == 1:
                dt = dtypes[name]
                out[name] = arr if arr.dtype == dt else _to_dtype(name, arr, dt)  # the common case, first
                continue
            if spec.width == 1:
                if arr.ndim == 2 and arr.shape[1] == 1:
                    arr = arr[:, 0]
                if arr.ndim != 1:
                    raise ChunkError("bad_channel_shape", f"channel {name!r} must be one value per point, got shape {arr.shape}")
            elif arr.ndim != 2 or arr.shape[1] != spec.width:
                raise ChunkError("bad_channel_shape", f"channel {name!r} must have shape ({n}, {spec.width}), got {arr.shape}")
            out[name] = _to_dtype(name, arr, self._dtypes[name])
        if self._imp_key is not None:
            src = importance_values(self.importance_source, chunk.channels)
            if src is not None:
                out[self._imp_key] = src
        return chunk.positions, out

    def _thin_step(self) -> int:
        now = time.monotonic()
        if now - self._fill_checked > 0.02:  # ring.stats() takes the lock: not per chunk
            st = self.ring.stats()
            self._fill = st.total_points / max(1, st.capacity)
            self._fill_checked = now
        for frac, k in THINNING:
            if self._fill >= frac:
                return k
        return 1

    def _enqueue(self, pos: np.ndarray, chans: dict[str, np.ndarray], trace: int, lo: float | None,
                 hi: float | None, rec: PointChunk | None = None, xf: Any = None) -> None:
        n = pos.shape[0]
        last = self.queue[-1] if self.queue else None
        # Only small chunks are coalesced: for big ones the copy costs more than the push saved.
        big = 2 * n >= self.coalesce_points
        if (big or last is None or last.solo or last.n + n > self.coalesce_points
                or last.channels and last.channels[-1].keys() != chans.keys()
                or last.positions[-1].dtype != pos.dtype or last.xf is not xf):
            last = _Batch(solo=big, xf=xf)
            self.queue.append(last)
            while len(self.queue) > self.queue_max_batches:
                old = self.queue.popleft()
                self.counters.drop("queue_overflow", old.n)
        last.positions.append(pos)
        last.channels.append(chans)
        last.traces.append(trace)
        if rec is not None:
            last.records.append(rec)
        last.n += n
        if lo is None:
            last.checked = False
        else:
            last.lo = min(last.lo, lo)
            last.hi = max(last.hi, hi)

    # ------------------------------------------------------------------ push
    def flush(self, max_batches: int | None = None) -> int:
        """Push queued batches into the ring (all, or at most ``max_batches``)."""
        if self.framer is not None and self.framer.waiting:  # waits over, transforms arrived
            for c, p, ch in self.framer.poll():
                self._admit(c, p, ch)
        done = 0
        while self.queue and (max_batches is None or done < max_batches):
            b = self.queue.popleft()
            if len(b.positions) == 1:
                pos, chans = b.positions[0], b.channels[0]
            else:
                pos = np.concatenate(b.positions)
                chans = {k: np.concatenate([c[k] for c in b.channels]) for k in b.channels[0]}
            n, lo, hi = b.n, b.lo, b.hi
            if not b.checked:
                pos, chans, lo, hi = self._finite(pos, chans)
                n = pos.shape[0]
                if not n:
                    done += 1
                    continue
                if b.xf is not None:
                    lo, hi = b.xf.bounds(lo, hi)
            t0 = time.monotonic_ns()
            if b.xf is None:
                res = self.ring.push(pos, trace_id=b.traces, value_range=(lo, hi), **chans)
            else:
                res = self.ring.push(pos, trace_id=b.traces, value_range=(lo, hi), transform=b.xf, **chans)
            t1 = time.monotonic_ns()
            self.pushes += 1
            refused = n - res.written - res.rejected
            self.counters.points_out += res.written
            if res.rejected:
                self.counters.drop("out_of_range", res.rejected)  # too far from the ring's origin
            if refused:
                self.counters.drop("ring_full", refused)
            self.ring_evicted += res.dropped - refused
            if self.spans is not None:
                for t in b.traces:
                    self.spans.record(t, "ring_committed", t0, t1, n)
            for r in b.records:
                self.record.offer(r)
            done += 1
        return done

    def finish_frames(self) -> None:
        """Stopping: clouds still waiting for transforms are placed if they can be, else
        dropped (``no_transform``), so the balance closes."""
        if self.framer is not None:
            for c, p, ch in self.framer.poll(final=True):
                self._admit(c, p, ch)

    @property
    def queued_points(self) -> int:
        return sum(b.n for b in self.queue)

    def stats_extra(self) -> dict[str, Any]:
        if not getattr(self.ring, "_closed", False):
            # the ring's counter in the same instant as points_out (ingest is the ring's only
            # writer, and this runs between pushes): the supervisor compares the two as of
            # this report, not the counter later against this report (docs/reliability.md)
            self._ring_written_seen = self.ring.total_written
        return {
            "ring_written_at_report": self._ring_written_seen,
            **(self.record.stats() if self.record is not None else {}),
            "messages_in": self.messages_in,
            "chunks_accepted": self.chunks_accepted,
            "rejected": dict(self.rejected),
            "rejected_messages": sum(self.rejected.values()),
            "ring_evicted": self.ring_evicted,
            "ring_pushes": self.pushes,
            "queue_batches": len(self.queue),
            "queued_points": self.queued_points,
            "transform_messages": self.transform_messages,
            **({"frames": self.framer.stats()} if self.framer is not None else {}),
        }


def _to_dtype(name: str, arr: np.ndarray, dt: np.dtype) -> np.ndarray:
    """Convert a channel to the ring's dtype (rgb: 16-bit scaled down, floats 0..1 scaled up)."""
    if arr.dtype == dt:
        return arr
    if dt == np.uint8:
        if arr.dtype.kind == "f":
            a = np.nan_to_num(arr.astype(np.float32, copy=False), nan=0.0, posinf=255.0, neginf=0.0)
            if a.size and float(a.max()) <= 1.0:
                a = a * 255.0
            return np.clip(np.rint(a), 0, 255).astype(np.uint8)
        if arr.dtype.itemsize > 1 or arr.dtype.kind == "i":
            return rgb_u8(arr)  # 16-bit colour (LAS): scaled down, unless it uses the 8-bit range
    return arr.astype(dt)


def prepare(cfg, info, log) -> None:
    """A standby's head start (:data:`KIND`'s ``prepare``): with ``frames.fixed`` set, import numba and
    load the compiled transform now (0.5-1 s of CPU), not when the stage is needed."""
    if cfg.frames is not None and cfg.frames.fixed:
        from ..frames import compiled

        compiled.load()


def main(ctx) -> None:
    """Stage loop (:data:`KIND`)."""
    from ..ring import PointRing

    icfg = ctx.cfg.ingest
    ring = PointRing.attach(ctx.info.ring_name)
    sock = ctx.zmq.socket(zmq.PULL)
    sock.setsockopt(zmq.RCVHWM, icfg.receive_hwm)
    sock.setsockopt(zmq.LINGER, 0)
    sock.bind(ctx.endpoints.ingest)
    tap = None
    if ctx.cfg.record is not None:
        from ..record.tap import RecordTap

        # the ring-internal importance values are not a channel of the data
        internal = () if any(c.name == IMPORTANCE_SLOT for c in ring.channels) else (IMPORTANCE_SLOT,)
        tap = RecordTap(ctx.zmq, ctx.endpoints.record, ctx.cfg.record.queue_messages, ctx.cfg.record.channels,
                        exclude=internal)
    ing = Ingestor(ring, max_chunk_points=icfg.max_chunk_points, coalesce_points=icfg.coalesce_points,
                   queue_max_batches=icfg.queue_max_batches, adaptive_thinning=icfg.adaptive_thinning,
                   importance_field=ctx.cfg.ring.importance_field, counters=ctx.counters,
                   spans=ctx.spans, log=ctx.log, frames=ctx.cfg.frames, record=tap)
    if ctx.cfg.render.color_by in ing.specs:
        ing.color_by = ctx.cfg.render.color_by
        ing.color_by_default = ctx.cfg.render.color_by == type(ctx.cfg.render).color_by
    ctx.on_beat.append(lambda: ctx.counters.extra.update(ing.stats_extra()))
    poller = zmq.Poller()
    poller.register(sock, zmq.POLLIN)
    # Drain at most this many messages before pushing, so a burst cannot starve the ring.
    burst = max(1, icfg.queue_max_batches)

    def take() -> None:
        take_messages(sock, ing.receive, burst)
        ing.flush()

    try:
        while ctx.running:
            ctx.beat()
            if not poller.poll(0 if ing.queue else 50):
                ing.flush()
                continue
            take()
        # Stopping: chunks the sources sent before they exited still reach the ring, so
        # the counts on both sides agree.
        ctx.drain_until_quiet(sock, take, STOP_QUIET_S, STOP_GRACE_S)
        ing.finish_frames()
        ing.flush()
    finally:
        ctx.counters.extra.update(ing.stats_extra())
        sock.close()
        if tap is not None:
            tap.close()
        ring.close()
