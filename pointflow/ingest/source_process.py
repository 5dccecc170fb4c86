"""The source stage: one transport, in its own process, pushing chunks to ingest.

Resolves the transport of ``cfg.sources[info.source_index]``, opens it, stamps each chunk
(source id, sequence number, trace id, send time) and sends it in the wire format on a
PUSH socket connected to ``endpoints.ingest``. A full send queue (ingest behind) never
blocks forever: live transports wait at most ``LIVE_SEND_WAIT_MS`` and then drop the chunk
(counted as ``hwm``); replay transports (``Transport.lossless``) wait, beating, until ingest
takes it or the stage is stopped. ``close()`` runs on every exit path. When the input ends
the stage says so (``finished``) and stays connected until the pipeline stops it: ZeroMQ
drops what the receiver had not yet taken when the sending side disconnects, so a replay
into a slow consumer (a sender waiting for its subscriber) would lose its tail.
"""
from __future__ import annotations

import time

import numpy as np
import zmq

from .. import wire
from ..chunk import ChunkError, PointChunk, new_trace_id
from ..frames import message as tfmsg
from ..frames.deskew import TIME_FIELDS
from ..stage.kinds import StageKind, register_stage_kind
from . import playback
from .transports import resolve_transport
from .transports.base import InputUnreadable

#: One stage per configured source (not ``external``, not an in-process ``api`` source);
#: started last and stopped first, in ``pointflow run`` and ``pointflow send``.
KIND = register_stage_kind(StageKind(
    name="source", main="pointflow.ingest.source_process:main", start_order=90, stop_wave=0, standby=True,
    roles=("pipeline", "send"),
    counters=("chunks_out", "reconnects",
              # a link source (docs/remote.md; remote/transit.py): its ledger starts again in a
              # restarted process
              "transport_link_sent", "transport_link_received", "transport_lost_in_transit",
              "transport_lost_chunks", "transport_joined_after",
              # a zenoh link source: arrived but dropped by its own bounded queue, dead senders
              "transport_receive_queue_full", "transport_receive_queue_full_chunks", "transport_senders_lost")))

#: How long a live source waits for room in the send queue before dropping a chunk.
LIVE_SEND_WAIT_MS = 100
#: Messages the PUSH socket queues before the wait/drop policy applies.
SEND_HWM = 64


def _stay_connected(ctx) -> None:
    """The input ended: say so, then idle (beating) until stopped, so the receiver takes
    every queued chunk before this end of the socket goes away."""
    ctx.input_ended()
    while ctx.running:
        ctx.beat()
        time.sleep(0.05)


def _send(ctx, sock, frames, lossless: bool) -> bool:
    """Send one message; False if it was dropped (never blocks past a stop request)."""
    waited = 0.0
    while True:
        try:
            sock.send_multipart(frames, zmq.NOBLOCK, copy=False)
            return True
        except zmq.Again:
            pass
        if not ctx.running or (not lossless and waited >= LIVE_SEND_WAIT_MS):
            return False
        sock.poll(20, zmq.POLLOUT)
        waited += 20
        ctx.beat()


#: A plugin's open() or chunks() inside one call this long is said (once per call): the
#: stage looks alive (its pulse thread beats) but no chunk can come and a stop waits for it.
STALL_S = 10.0


class _StallWatch:
    """Says, from a thread of its own, when a plugin transport's ``open()`` has not returned
    or its ``chunks()`` has not yielded for :data:`STALL_S` (docs/plugins.md: chunks() yields
    None while idle, never blocking more than ~100 ms). Built-in transports are not watched."""

    def __init__(self, log, source_id: str, transport: str):
        import threading

        self.log, self.source_id, self.transport = log, source_id, transport
        self.what: str | None = None
        self.t0 = 0.0
        self.said = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="pointflow-stall-watch", daemon=True)
        self._thread.start()

    def enter(self, what: str) -> None:
        self.t0, self.said, self.what = time.monotonic(), False, what

    def leave(self) -> None:
        self.what = None

    def _run(self) -> None:
        while not self._stop.wait(1.0):
            what, t0 = self.what, self.t0
            if what is not None and not self.said and time.monotonic() - t0 >= STALL_S:
                self.said = True
                hint = ("open() should connect or fail with a clear error" if what == "open()" else
                        "chunks() should yield None while idle and never block more than ~100 ms, or the stage "
                        "cannot stop on time (docs/plugins.md)")
                self.log.warning("source %r: transport %s: %s has not %s for %.0f s; %s", self.source_id,
                                 self.transport, what, "returned" if what == "open()" else "yielded",
                                 time.monotonic() - t0, hint)

    def close(self) -> None:
        self._stop.set()


def main(ctx) -> None:
    """Stage loop (:data:`KIND`)."""
    idx = ctx.info.source_index if ctx.info.source_index >= 0 else 0
    scfg = ctx.cfg.sources[idx]
    cls = resolve_transport(scfg.transport)
    source_id = scfg.name or f"source{idx}"
    transport = cls(dict(scfg.options), source_id)
    lossless = bool(getattr(transport, "lossless", False))
    fcfg = ctx.cfg.frames
    if fcfg.fixed and fcfg.deskew != "off":  # per-point times survive the channel filter
        extra = (fcfg.deskew.field,) if not isinstance(fcfg.deskew, str) else TIME_FIELDS
        transport.keep_fields = tuple(transport.keep_fields) + extra
    transport.wants_transforms = bool(fcfg.fixed)
    transport.ring_capacity = ctx.cfg.ring.max_points
    frame_id = scfg.frame_id or ""
    # which configured source each point came from, for per-source visibility (render/view/protocol.py)
    mark = "source_index" in ctx.cfg.ring_channels()
    tf_sent = 0
    sock = ctx.zmq.socket(zmq.PUSH)
    sock.setsockopt(zmq.SNDHWM, SEND_HWM)
    sock.setsockopt(zmq.LINGER, 2000)  # let the last chunks of a finished replay go out
    sock.connect(ctx.endpoints.ingest)
    view_tf = None  # the same transforms to the render stage, for a camera that follows a frame
    if fcfg.fixed and ctx.endpoints.view_transforms:
        view_tf = ctx.zmq.socket(zmq.PUSH)
        view_tf.setsockopt(zmq.SNDHWM, 64)
        view_tf.setsockopt(zmq.LINGER, 0)
        view_tf.connect(ctx.endpoints.view_transforms)

    def _stats() -> None:
        ctx.counters.extra.update({f"transport_{k}": v for k, v in transport.counters.items()})
        ctx.counters.extra["chunks_sent"] = seq
        if tf_sent:
            ctx.counters.extra["transforms_sent"] = tf_sent

    ctx.on_beat.append(_stats)
    seq = 0
    control = None  # the replay's control path (pause, seek, step, rate, loop): ingest/playback.py
    clock = transport.playback if getattr(transport, "seekable", False) else None
    from .transports import BUILTINS

    watch = _StallWatch(ctx.log, source_id, scfg.transport) if scfg.transport not in BUILTINS else None
    try:
        if watch is not None:
            watch.enter("open()")
        transport.open()
        if watch is not None:
            watch.leave()
        if clock is not None:
            clock.configure(ctx.cfg.playback)
            transport.counters.update(clock.counters())
            if ctx.endpoints.playback:
                control = ctx.zmq.socket(zmq.REP)
                control.setsockopt(zmq.LINGER, 0)
                control.bind(playback.playback_endpoint(ctx.endpoints.playback, idx))
        it = transport.chunks()
        while ctx.running:
            if control is not None:
                playback.serve(control, clock, ctx.log, ctx.counters)
                transport.counters.update(clock.counters())
            t0 = time.monotonic_ns()
            try:
                if watch is not None:
                    watch.enter("chunks()")
                chunk = next(it)
            except StopIteration:
                _stay_connected(ctx)
                break
            finally:
                if watch is not None:
                    watch.leave()
            ctx.beat()
            if chunk is None:
                continue
            if isinstance(chunk, tfmsg.Transforms):  # on the same socket, in order with the clouds
                if chunk.transforms:
                    encoded = tfmsg.encode(chunk, source_id)
                    if view_tf is not None:
                        try:  # never waits: the view may not follow anything
                            view_tf.send_multipart(encoded, zmq.NOBLOCK)
                        except zmq.Again:
                            pass
                    if _send(ctx, sock, encoded, lossless):
                        tf_sent += len(chunk.transforms)
                    else:  # a live source behind ingest: counted like dropped chunks
                        ctx.counters.extra["transforms_dropped"] = ctx.counters.extra.get("transforms_dropped", 0) + len(chunk.transforms)
                continue
            if not isinstance(chunk, PointChunk):  # a plugin's mistake: said here, naming the source
                transport.reject("bad_chunk", f"chunks() yielded a {type(chunk).__name__}, expected a PointChunk, "
                                              f"Transforms or None")
                continue
            try:  # cheap (no per-point work): a bad chunk is named at its source, not at ingest
                chunk.validate(ctx.cfg.ingest.max_chunk_points)
            except ChunkError as exc:
                transport.reject(exc.reason, f"chunks() yielded a bad chunk: {exc}"
                                 + (" (ingest.max_chunk_points; yield it in parts)" if exc.reason == "too_large" else ""))
                continue
            if frame_id and not chunk.frame_id:
                chunk.frame_id = frame_id
            t1 = time.monotonic_ns()
            n = len(chunk)
            chunk.source_id = chunk.source_id or source_id
            if mark:
                chunk.channels["source_index"] = np.full(n, idx, np.float32)
            chunk.seq = seq
            chunk.trace_id = new_trace_id()
            chunk.t_sent_ns = time.monotonic_ns()
            ctx.spans.record(chunk.trace_id, "transport_receive", t0, t1, n)
            try:
                frames = wire.encode(chunk)
            except Exception as exc:  # noqa: BLE001 - a bad chunk from a plugin is dropped, not fatal
                ctx.counters.points_in += n
                ctx.counters.drop("encode_error", n)
                ctx.log.warning("transport %s produced an unencodable chunk: %s", scfg.transport, exc)
                continue
            # counted in and out together (no heartbeat in between), so every report
            # balances: points_in = points_out + drops
            sent = _send(ctx, sock, frames, lossless)
            ctx.counters.points_in += n
            if sent:
                ctx.counters.points_out += n
                seq += 1
            else:
                ctx.counters.drop("hwm", n)
    except InputUnreadable as exc:  # restarting cannot help: the run fails, naming the inputs
        ctx.fail_run(str(exc))
    finally:
        if watch is not None:
            watch.close()
        try:
            transport.close()
        finally:
            _stats()
            sock.close()
            if control is not None:
                control.close(0)
            if view_tf is not None:
                view_tf.close(0)
