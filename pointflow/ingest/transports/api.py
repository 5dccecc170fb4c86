"""``api``: clouds sent from the caller's own Python code (``Pipeline.send``).

Unlike every other transport, an ``api`` source runs *inside the process that holds the
Pipeline* (the supervisor's process), not in a source process of its own: the caller's
arrays are encoded there and pushed straight to ingest's PULL socket, the same wire format
and socket a source stage uses, so ingest cannot tell them apart. No extra process and no
extra hop: large arrays are copied once, into reused staging buffers that ZeroMQ sends
without a further copy (the caller may reuse its arrays as soon as ``send`` returns), then
the kernel's socket copies and ingest's write into the ring.

The supervisor keeps an :class:`ApiSource` in its stage table like a source stage
(``kind: source``): its counters are in ``stats()`` and in the accounting
(``sources_received`` = ``sources_forwarded`` + ``sources_dropped``), it is stopped first
(its queue flushed to ingest before ingest stops), and ``Pipeline.send`` to a name no source
has adds one at run time (no process to start, so nothing can fail to start).

Backpressure (``backpressure`` option):

* ``block`` (default; replays, simulations that must not lose a cloud): ``send`` waits
  while ingest is behind (ZeroMQ's high-water mark is reached); the time waited is counted
  (``send_blocked_ms``).
* ``drop_oldest`` (live data): ``send`` never waits; clouds wait in a queue of
  ``queue_clouds`` that a sender thread empties; when it is full the oldest is dropped,
  counted as ``drops.drop_oldest``.

Thread safety: ZeroMQ sockets are not thread-safe, so one lock serialises every use of the
socket (``block``), or only the sender thread touches it (``drop_oldest``); any number of
threads may call ``send`` at once.
"""
from __future__ import annotations

import collections
import dataclasses
import threading
import time
from typing import Any, Callable, Iterator, Literal, Mapping, Optional, Sequence

import numpy as np
import zmq

from ... import wire
from ...chunk import SUPPORTED_DTYPES, PointChunk, new_trace_id
from ...errors import Error
from ...frames import message as tfmsg
from ...typed import Bound, check
from .base import Transport

#: Messages ZeroMQ queues towards ingest before ``block`` waits (as a source stage's SEND_HWM).
SEND_HWM = 64
#: ``drop_oldest``: ZeroMQ's own queue is kept short, so the backlog sits in our queue
#: where the oldest cloud can be dropped (ZeroMQ can only refuse the newest).
DROP_OLDEST_HWM = 2
#: On close, how long queued clouds may take to reach ingest.
FLUSH_S = 5.0
#: Staging buffers of one source may hold this many bytes in all (see :class:`_Staging`).
STAGING_MAX_BYTES = 256 << 20


class _Buffer:
    __slots__ = ("mem", "tracker", "busy")

    def __init__(self, nbytes: int):
        self.mem = np.empty(nbytes, np.uint8)
        self.tracker: Any = None   # ZeroMQ's MessageTracker of the message sent from it
        self.busy = True           # filled, not yet handed to ZeroMQ (queued, or being sent)

    def free(self) -> bool:
        return not self.busy and (self.tracker is None or self.tracker.done)


class _Staging:
    """Where large arrays are copied before ZeroMQ sends them without a further copy.

    The caller may reuse its arrays once ``send`` returns, so one copy is needed. Into a
    fresh ZeroMQ message (``copy=True``) it page-faults new memory on every cloud; here it
    goes into buffers that are reused once ZeroMQ is done with them (a MessageTracker), so
    the pages are warm: measured 1.5-2x the points/s of ``copy=True`` for 100k-point clouds
    (bench/bench_api.py). Frames under :data:`pointflow.wire.ZERO_COPY_MIN_BYTES` are
    copied by ZeroMQ as usual. Used under the source's lock."""

    def __init__(self, max_bytes: int = STAGING_MAX_BYTES):
        self.buffers: list[_Buffer] = []
        self.max_bytes = max_bytes

    def take(self, nbytes: int, wait: bool, closed) -> Optional[_Buffer]:
        """A free buffer of at least ``nbytes`` (marked busy), a new one while the total
        allows, else (``wait``) the oldest in flight once ZeroMQ released it; None when none
        is free and ``wait`` is False (the caller copies the plain way)."""
        for b in self.buffers:
            if b.mem.nbytes >= nbytes and b.free():
                b.busy, b.tracker = True, None
                return b
        total = sum(b.mem.nbytes for b in self.buffers)
        if total + nbytes > self.max_bytes:  # make room: drop free buffers too small for this size
            self.buffers = [b for b in self.buffers if not (b.free() and b.mem.nbytes < nbytes)]
            total = sum(b.mem.nbytes for b in self.buffers)
        if total + nbytes <= self.max_bytes:
            b = _Buffer(nbytes)
            self.buffers.append(b)
            return b
        if not wait:
            return None
        while True:  # every buffer is in flight: the oldest goes first (ZeroMQ sends in order)
            for b in self.buffers:
                if b.mem.nbytes >= nbytes and not b.busy and b.tracker is not None:
                    while not b.tracker.done:
                        if closed():
                            raise RuntimeError("api source closed while waiting for ingest")
                        try:
                            b.tracker.wait(0.05)
                        except zmq.NotDone:
                            pass
                    b.busy, b.tracker = True, None
                    return b
            if closed():
                raise RuntimeError("api source closed while waiting for ingest")
            time.sleep(0.001)  # only busy (queued) buffers: drop_oldest never waits here

    def stage(self, frames: list, wait: bool, closed) -> tuple[list, Optional[_Buffer]]:
        """``frames`` with every large data frame copied into one staging buffer."""
        big = [i for i, f in enumerate(frames) if not isinstance(f, bytes) and f.nbytes >= wire.ZERO_COPY_MIN_BYTES]
        if not big:
            return frames, None
        need = sum(frames[i].nbytes for i in big)
        b = self.take(need, wait, closed)
        if b is None:
            return [f if isinstance(f, bytes) else bytes(f) for f in frames], None
        out, off = list(frames), 0
        for i in big:
            nb = frames[i].nbytes
            view = b.mem[off:off + nb]
            view[:] = np.frombuffer(frames[i], np.uint8)
            out[i] = memoryview(view)
            off += nb
        return out, b


class SendError(Error, ValueError):
    """Bad input to ``send``/``send_transforms``: the message names the argument and what
    was expected. Nothing of the call was sent; the pipeline goes on."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


@dataclasses.dataclass
class ApiOptions:
    #: block: ``send`` waits while ingest is behind; drop_oldest: never waits, the oldest
    #: queued cloud is dropped (counted) when ``queue_clouds`` wait.
    backpressure: Literal["block", "drop_oldest"] = "block"
    #: drop_oldest: clouds that may wait for ingest before the oldest is dropped.
    queue_clouds: int = dataclasses.field(default=8, metadata=check(Bound(1, 100_000)))


class ApiTransport(Transport):
    """The ``api`` kind in the config (``transport: api``). It runs in the caller's process
    (:class:`ApiSource`), so the supervisor never starts a source process for it."""

    name = "api"
    options_schema = ApiOptions
    lossless = True
    #: The supervisor keeps an :class:`ApiSource` in its own process instead of a stage.
    in_process = True

    def chunks(self) -> Iterator[Optional[PointChunk]]:  # pragma: no cover - never run as a stage
        raise RuntimeError("the api transport runs inside the process that holds the Pipeline")


# --------------------------------------------------------------------------- input checks
def _positions(positions: Any) -> np.ndarray:
    """The positions as an (n, 3) float32/float64 array. A numpy array of another dtype is
    refused (the caller chose it); nested lists or tuples of numbers are read as float64."""
    if not isinstance(positions, np.ndarray):
        given = type(positions).__name__
        try:
            positions = np.asarray(positions)
        except Exception as exc:  # noqa: BLE001 - anything numpy cannot read
            raise SendError("bad_positions", f"positions: expected a float32 or float64 numpy array of shape (n, 3), "
                                             f"got {given} ({exc})") from None
        if positions.dtype.kind not in "iuf":
            raise SendError("bad_dtype", f"positions: expected a float32 or float64 numpy array of shape (n, 3), "
                                             f"got {given}" + (f" of {positions.dtype}" if given in ("list", "tuple") else ""))
        positions = positions.astype(np.float64, copy=False)
    if positions.dtype not in (np.float32, np.float64):
        raise SendError("bad_dtype", f"positions: expected dtype float32 or float64, got {positions.dtype} "
                                     "(convert with positions.astype(np.float32))")
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise SendError("bad_shape", f"positions: expected shape (n, 3), got {positions.shape}")
    return positions


def _check_rgb(arr: np.ndarray, n: int) -> None:
    """``rgb`` as the ring stores it can hold it: (n, 3), integers 0..255 or 0..65535 (16-bit,
    scaled down) or floats (0..1 scaled up). Refused here, with nothing sent, rather than at
    ingest (dropped) or clipped (int -5 and 300 became 0 and 1)."""
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise SendError("bad_channel_shape", f"channel 'rgb': expected shape ({n}, 3) (red, green, blue), got {arr.shape}")
    if arr.dtype.kind in "iu" and arr.size:
        lo, hi = int(arr.min()), int(arr.max())
        if lo < 0 or hi > 65535:
            raise SendError("bad_value", f"channel 'rgb': integer colour must be 0..255 (8-bit) or 0..65535 "
                                         f"(16-bit), got values from {lo} to {hi}")


def check_cloud(positions: Any, channels: Mapping[str, Any], frame: Any, stamp_ns: Any,
                allowed: Optional[Sequence[str]] = None) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The arrays of one ``send`` call, checked; :class:`SendError` naming the argument."""
    pos = _positions(positions)
    n = pos.shape[0]
    chans: dict[str, np.ndarray] = {}
    for name, arr in channels.items():
        if allowed is not None and name not in allowed:
            kept = ", ".join(allowed) or "none"
            raise SendError("unknown_channel", f"channel {name!r}: not kept by this pipeline's ring (it keeps: {kept}); "
                                               "name it in render.color_by or ring.extra_channels")
        if not isinstance(arr, np.ndarray):
            try:
                arr = np.asarray(arr)
            except Exception as exc:  # noqa: BLE001
                raise SendError("bad_channel", f"channel {name!r}: expected a numpy array, got {type(arr).__name__} ({exc})") from None
        if arr.dtype.name not in SUPPORTED_DTYPES:
            raise SendError("bad_dtype", f"channel {name!r}: dtype {arr.dtype} is not supported "
                                         f"(expected one of {', '.join(SUPPORTED_DTYPES)})")
        if arr.ndim not in (1, 2) or arr.shape[0] != n:
            raise SendError("length_mismatch", f"channel {name!r}: expected shape ({n},) or ({n}, k) to match "
                                               f"positions' {n} points, got {arr.shape}")
        if name == "rgb":
            _check_rgb(arr, n)
        chans[name] = arr
    if frame is not None and (not isinstance(frame, str) or not frame):
        raise SendError("bad_frame", f"frame: expected a frame name (a non-empty str) or None, got {frame!r}")
    if stamp_ns is not None and (not isinstance(stamp_ns, (int, np.integer)) or isinstance(stamp_ns, bool)
                                 or not 0 <= int(stamp_ns) < 2**63):
        raise SendError("bad_stamp", f"stamp_ns: expected an integer of nanoseconds since the epoch (>= 0) or None, "
                                     f"got {stamp_ns!r}")
    return pos, chans


def check_transforms(transforms: Any) -> tfmsg.Transforms:
    """``send_transforms``' argument (a list of dicts as in docs/wire-format.md, or of
    :class:`pointflow.frames.message.Transform`), checked like ingest checks the message."""
    if isinstance(transforms, (dict, tfmsg.Transform)):
        transforms = [transforms]
    if not isinstance(transforms, (list, tuple)):
        raise SendError("bad_transform", "transforms: expected a list of transforms (dicts with parent, child, stamp_ns, "
                                         f"translation, rotation), got {type(transforms).__name__}")
    items = [t.to_json() if isinstance(t, tfmsg.Transform) else t for t in transforms]
    for i, it in enumerate(items):  # JSON-like numbers for the message checks (numpy arrays welcome)
        if isinstance(it, dict):
            it = dict(it)
            for k in ("translation", "rotation"):
                if isinstance(it.get(k), (np.ndarray, tuple)):
                    it[k] = np.asarray(it[k]).tolist()
            if isinstance(it.get("stamp_ns"), np.integer):
                it["stamp_ns"] = int(it["stamp_ns"])
            items[i] = it
    try:
        return tfmsg.decode({"transforms": items})
    except tfmsg.TransformMessageError as exc:
        raise SendError("bad_transform", exc.message) from None


# --------------------------------------------------------------------------- the source
class ApiSource:
    """One ``api`` source: checks, encodes and sends the caller's clouds to ingest.

    ``endpoint`` is ingest's (or, under ``pointflow.connect``, the link sender's) PULL
    socket. ``channels`` limits the channel names accepted (the ring's), None = any."""

    def __init__(self, name: str, endpoint: str, options: Optional[dict] = None, *,
                 channels: Optional[Sequence[str]] = None, max_chunk_points: int = 5_000_000,
                 frame_id: Optional[str] = None, failed: Optional[Callable[[], Optional[BaseException]]] = None):
        """``failed``: what the pipeline's failure is (an exception to raise), or None while it
        runs; a send raises it rather than wait for an ingest that will not come back."""
        self.name = name
        self._failed = failed or (lambda: None)
        #: The source's ``frame_id`` from the config: the frame of clouds sent without one.
        self.frame_id = frame_id or ""
        self.o = ApiOptions(**(options or {}))
        self.allowed = list(channels) if channels is not None else None
        self.max_chunk_points = max_chunk_points
        self._ctx = zmq.Context()  # its own: term() on close waits until the last messages left
        self._sock = self._ctx.socket(zmq.PUSH)
        self._sock.setsockopt(zmq.SNDHWM, DROP_OLDEST_HWM if self.o.backpressure == "drop_oldest" else SEND_HWM)
        self._sock.setsockopt(zmq.LINGER, int(FLUSH_S * 1000))
        self._sock.connect(endpoint)
        self._lock = threading.Lock()       # the socket (block) and every counter
        self._cond = threading.Condition(self._lock)
        #: drop_oldest: (frames, points (> 0) or -transforms, staging buffer or None)
        self._queue: collections.deque = collections.deque()
        self._closed = False
        self.seq = 0
        self.points_in = 0
        self.points_out = 0
        self.drops: collections.Counter[str] = collections.Counter()
        self.rejected: collections.Counter[str] = collections.Counter()
        self.transforms_sent = 0
        self.blocked_ns = 0
        self._thread: Optional[threading.Thread] = None
        self._inflight = 0
        self._flush_end = 0.0
        self._staging = _Staging()
        if self.o.backpressure == "drop_oldest":
            self._thread = threading.Thread(target=self._pump, name=f"pointflow-api-{name}", daemon=True)
            self._thread.start()

    # ------------------------------------------------------------------ sending
    def send(self, positions: Any, frame: Optional[str] = None, stamp_ns: Optional[int] = None,
             **channels: Any) -> int:
        """Send one cloud; returns its point count once it is handed over (``block``) or
        queued (``drop_oldest``). :class:`SendError` on bad input (counted in ``rejected``)."""
        exc_failed = self._failed()
        if exc_failed is not None:
            raise exc_failed
        try:
            pos, chans = check_cloud(positions, channels, frame, stamp_ns, self.allowed)
        except SendError as exc:
            with self._lock:
                self.rejected[exc.reason] += 1
            raise
        n = pos.shape[0]
        if n == 0:
            return 0
        step = self.max_chunk_points
        for a in range(0, n, step):  # clouds larger than ingest takes in one chunk: in parts
            b = min(n, a + step)
            part = (pos, chans) if (a == 0 and b == n) else (pos[a:b], {k: v[a:b] for k, v in chans.items()})
            self._send_chunk(*part, frame or self.frame_id, int(stamp_ns or 0))
        return n

    def _send_chunk(self, pos: np.ndarray, chans: dict, frame: str, stamp: int) -> None:
        chunk = PointChunk(pos, chans, self.name, 0, new_trace_id(), 0, 0, stamp, frame)
        n = chunk.n
        with self._lock:
            if self._closed:
                raise RuntimeError(f"api source {self.name!r} is closed (the pipeline stopped)")
            chunk.seq = self.seq
            chunk.t_sent_ns = time.monotonic_ns()
            # the caller may reuse its arrays once send returns: large ones are copied once,
            # into a staging buffer that ZeroMQ then sends without copying
            frames, buf = self._staging.stage(wire.encode(chunk), self._thread is None, lambda: self._closed)
            if self._thread is not None:
                self._queue.append((frames, n, buf))
                self.seq += 1
                self.points_in += n
                self._trim()
                self._cond.notify()
                return
            self._send_blocking(frames, buf)
            self.seq += 1
            self.points_in += n
            self.points_out += n

    def send_transforms(self, transforms: Any) -> int:
        """Send transforms (in order with the clouds); returns how many."""
        try:
            batch = check_transforms(transforms)
        except SendError as exc:
            with self._lock:
                self.rejected[exc.reason] += 1
            raise
        if not batch.transforms:
            return 0
        frames = tfmsg.encode(batch, self.name)
        with self._lock:
            if self._closed:
                raise RuntimeError(f"api source {self.name!r} is closed (the pipeline stopped)")
            if self._thread is not None:
                self._queue.append((frames, -len(batch.transforms), None))
                self._cond.notify()
            else:
                self._send_blocking(frames, None)
                self.transforms_sent += len(batch.transforms)
        return len(batch.transforms)

    def _send_blocking(self, frames: list, buf: Optional[_Buffer]) -> None:
        """Under the lock: hand one message to ZeroMQ, waiting while ingest is behind.
        Staged frames go without a copy (their buffer is reused once ZeroMQ is done);
        small ones are copied into ZeroMQ's message."""
        copy = buf is None
        try:
            self._put(frames, buf, copy)
            return
        except zmq.Again:
            pass
        t0 = time.monotonic_ns()
        try:
            while True:
                self._sock.poll(50, zmq.POLLOUT)
                try:
                    self._put(frames, buf, copy)
                    return
                except zmq.Again:
                    failed = self._failed()
                    if self._closed or failed is not None:
                        if buf is not None:
                            buf.busy = False
                        if failed is not None:  # ingest will not come back: the pipeline stopped
                            raise failed from None
                        raise RuntimeError(f"api source {self.name!r} closed while waiting for ingest") from None
        finally:
            self.blocked_ns += time.monotonic_ns() - t0

    def _put(self, frames: list, buf: Optional[_Buffer], copy: bool) -> None:
        if buf is None:
            self._sock.send_multipart(frames, zmq.NOBLOCK, copy=copy)
            return
        buf.tracker = self._sock.send_multipart(frames, zmq.NOBLOCK, copy=False, track=True)
        buf.busy = False

    def _trim(self) -> None:
        """drop_oldest, under the lock: beyond ``queue_clouds`` the oldest cloud goes."""
        clouds = sum(1 for _, m, _b in self._queue if m > 0)
        while clouds > self.o.queue_clouds:
            for i, (_, m, b) in enumerate(self._queue):
                if m > 0:
                    del self._queue[i]
                    if b is not None:
                        b.busy = False
                    self.drops["drop_oldest"] += m
                    clouds -= 1
                    break

    def _pump(self) -> None:
        """drop_oldest's sender thread: the only user of the socket. The message being sent
        is out of the queue (``_inflight``), so only waiting clouds are ever dropped."""
        while True:
            with self._lock:
                while not self._queue and not self._closed:
                    self._cond.wait(0.2)
                if not self._queue:
                    return
                frames, m, buf = self._queue.popleft()
                self._inflight = max(m, 0)
            sent = False
            while not sent:
                try:
                    tracker = self._sock.send_multipart(frames, zmq.NOBLOCK, copy=False, track=buf is not None)
                    if buf is not None:
                        with self._lock:
                            buf.tracker, buf.busy = tracker, False
                    sent = True
                except zmq.Again:
                    if self._closed and time.monotonic() > self._flush_end:
                        break
                    self._sock.poll(20, zmq.POLLOUT)
            with self._lock:
                self._inflight = 0
                if not sent:
                    if buf is not None:
                        buf.busy = False
                    self.drops["unsent_at_stop"] += max(m, 0)
                    return
                if m > 0:
                    self.points_out += m
                else:
                    self.transforms_sent += -m

    # ------------------------------------------------------------------ state
    @property
    def closed(self) -> bool:
        return self._closed

    def stats(self) -> dict[str, Any]:
        """As a source stage's heartbeat stats (``points_in`` = ``points_out`` + drops + queued)."""
        with self._lock:
            queued = sum(m for _, m, _b in self._queue if m > 0) + self._inflight
            return {"points_in": self.points_in - queued, "points_out": self.points_out, "drops": dict(self.drops),
                    "rejected": dict(self.rejected), "chunks_sent": self.seq, "transforms_sent": self.transforms_sent,
                    "backpressure": self.o.backpressure, "queued_points": queued,
                    "send_blocked_ms": round(self.blocked_ns / 1e6, 3), "in_process": True}

    def close(self, timeout_s: float = FLUSH_S) -> None:
        """Flush what was accepted to ingest (at most ``timeout_s``), then close; what could
        not go is counted (``unsent_at_stop``). Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._flush_end = time.monotonic() + timeout_s
            self._closed = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout_s + 1)
            with self._lock:
                left = sum(m for _, m, _b in self._queue if m > 0)
                if left:
                    self.drops["unsent_at_stop"] += left
                self._queue.clear()
        self._sock.close(linger=int(timeout_s * 1000))
        self._ctx.term()  # returns once ZeroMQ handed the last messages to ingest (or linger ran out)


__all__ = ["ApiTransport", "ApiOptions", "ApiSource", "SendError", "check_cloud", "check_transforms"]
