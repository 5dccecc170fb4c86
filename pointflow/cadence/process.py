"""The cadence stage: snapshot the ring at a steady rate and hand slabs to the renderer.

Each tick (absolute deadlines, see :class:`~pointflow.cadence.ticker.Ticker`) copies what
changed in the ring into the slab the renderer does not hold and sends the handoff. A tick
is skipped (and counted) when it could not be served in time (``late``), when the renderer
holds both slabs (``renderer_busy``) or when no renderer is connected (``no_reader``), so a
slow renderer never builds a backlog.

The release socket also carries the render stage's control messages
(:mod:`pointflow.cadence.messages`): ``hello`` (renderer (re)started → ``reset_reader``) and
``frame`` (frame time → adaptive interval). The cadence reads that socket itself and
forwards slab releases to the :class:`~pointflow.ring.handoff.SlabWriter` over an inproc pair.
"""
from __future__ import annotations

import collections
import logging
import time
from typing import Any, Optional

import numpy as np
import zmq

from ..stage.kinds import StageKind, register_stage_kind
from .messages import ControlMessageError, FrameTime, Hello, Idle, decode_control
from .policy import HardwareInfo, PolicyDecision, detect_hardware, resolve_policy, tick_interval_ms
from .ticker import Clock, Sleep, Tick, Ticker

#: Smoothing factor of the renderer frame-time EMA (adaptive mode).
KIND = register_stage_kind(StageKind(name="cadence", main="pointflow.cadence.process:main", start_order=20,
                                    stop_wave=2, standby=True, counters=("published",)))

FRAME_EMA_ALPHA = 0.15
#: latest_only: publish anyway when the renderer has shown no progress for this long, or
#: for 10 of its slowest recent frames if that is longer (a renderer that keeps its slab
#: must not starve). It was 250 ms or 3 frame *EMAs*: on a loaded machine one frame in a few
#: took 2-3x the EMA (and a restarted renderer's first, full frame several seconds), the
#: cadence handed out its second slab mid-frame, and that snapshot waited in the queue
#: until the frame ended: chunks reached the screen after up to 3 frames (send -> frame p99
#: 2.4x frame p99). Nothing needs the early publish now: a renderer whose releases and frame
#: reports were lost says so itself (``idle``, within 0.5 s), and one stuck mid-frame is
#: restarted by the supervisor (``hello``).
STALL_S = 5.0
#: A handoff the renderer says it never got, sent at least this long ago (or the stall
#: window, if longer), was lost on the way (a connection to a renderer that died).
LOST_AFTER_S = 2.0
STALL_FRAMES = 10.0
RECENT_FRAMES = 32
#: While the renderer draws (or before it can), bring the next slab up to date at most this
#: often (:mod:`pointflow.cadence.prefill`), so the snapshot at the frame's end copies only
#: the last few ticks' changes.
PREFILL_S = 0.05
_RELEASE_TAG = b"pf.ring.release/1"  # pointflow.ring.handoff.RELEASE_TAG: [tag, int64 (slab, seq)]
_WINDOW = 1024  # ticks kept for the jitter / rate statistics


class Cadence:
    """The tick loop, independent of the stage plumbing (tests drive it directly).

    ``release_sock`` is the bound PULL the renderer's releases and control messages arrive on;
    ``ready_sock`` the PUSH to the renderer. ``spans`` needs ``record(trace_id, event, t0, t1, n)``.

    ``latest_only`` (default): publish only when the renderer has finished (released, or
    reported the frame of) every handoff sent so far; otherwise skip (``renderer_pending``).
    Without it the second slab is filled while the renderer draws the first and then waits a
    whole frame in the queue, so a slow renderer always shows data one frame older than
    necessary; with it the renderer gets a snapshot at most one tick old when it is ready.
    """

    def __init__(self, ring, slabs, ready_sock: zmq.Socket, release_sock: zmq.Socket, zctx: zmq.Context,
                 cfg: Any, decision: PolicyDecision, *, spans: Any = None,
                 clock: Clock = time.monotonic, sleep: Sleep = time.sleep,
                 log: Optional[logging.Logger] = None, latest_only: bool = True,
                 wait_for_renderer: bool = False):
        from .prefill import PrefillWriter  # noqa: PLC0415 - keep module import light

        self.cfg = cfg
        self.decision = decision
        self.spans = spans
        self.clock = clock
        self.log = log or logging.getLogger("pointflow.cadence")
        self.release_in = release_sock
        # Releases are forwarded to the writer over inproc, so control messages never reach it.
        addr = f"inproc://pf-cadence-release-{id(self)}"
        self._fwd_pull = zctx.socket(zmq.PULL)
        self._fwd_pull.setsockopt(zmq.LINGER, 0)
        self._fwd_pull.bind(addr)
        self._fwd_push = zctx.socket(zmq.PUSH)
        self._fwd_push.setsockopt(zmq.LINGER, 0)
        self._fwd_push.connect(addr)
        self.writer = PrefillWriter(ring, slabs, ready_sock, self._fwd_pull)
        self._t_copy = clock()  # the last prefill or publish
        self.frame_ema_ms: Optional[float] = None
        self._recent_frames_ms: collections.deque = collections.deque(maxlen=RECENT_FRAMES)
        self.interval_ms = tick_interval_ms(cfg, decision, None)
        self.ticker = Ticker(self.interval_ms / 1000.0, clock=clock, sleep=sleep)
        self.t_start = clock()
        self.ticks = 0
        self.published = 0
        self.points_out = 0
        self.skipped: collections.Counter[str] = collections.Counter()
        self.hellos = 0
        self._frame_reports = 0  # frame messages from the current renderer
        self.resyncs = 0        # idle messages that freed a slab the renderer no longer held
        self.lost_handoffs = 0  # handoffs the renderer never got (freed after an idle message)
        self._sent_at = [float("-inf")] * 2  # when each slab was last handed out (clock)
        self.bad_messages = 0
        self.latest_only = latest_only
        #: Publish nothing until the renderer has said something (hello, a frame report, a
        #: release, idle): at a pipeline's start its socket is bound seconds before it can
        #: draw (device, warm-up), and a snapshot sent then was stale when it was drawn.
        self.renderer_heard = not wait_for_renderer
        self.last_pub_seq = 0       # newest handoff sent
        self.done_seq = 0           # newest handoff the renderer released or reported a frame for
        self._t_progress = clock()
        self._late = collections.deque(maxlen=_WINDOW)
        self._tick_times = collections.deque(maxlen=_WINDOW)
        self._pub_times = collections.deque(maxlen=_WINDOW)

    # -------------------------------------------------------------- messages
    def drain(self, timeout_s: float = 0.0) -> int:
        """Wait up to ``timeout_s`` for messages on the release socket and handle all pending."""
        n = 0
        if timeout_s > 0 and not self.release_in.poll(max(1, int(timeout_s * 1000)), zmq.POLLIN):
            return 0
        while True:
            try:
                frames = self.release_in.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return n
            n += 1
            self.handle(frames)

    def handle(self, frames: list[bytes]) -> None:
        self.renderer_heard = True
        try:
            msg = decode_control(frames)
        except ControlMessageError as exc:
            self.bad_messages += 1
            if self.bad_messages <= 10:
                self.log.warning("release socket: %s (message dropped, %d so far)", exc, self.bad_messages)
            return
        if msg is None:  # a slab release (or junk the writer ignores)
            if (not self._frame_reports and len(frames) == 2 and bytes(frames[0]) == _RELEASE_TAG
                    and len(frames[1]) == 16):
                # a renderer that reports its frames is done when it says so: it gives its
                # slab back as soon as its frame no longer reads it, which on lavapipe is
                # ~1 s before the GPU work ends, and a snapshot taken then waited that long
                self._done(int(np.frombuffer(bytes(frames[1]), dtype="<i8")[1]))
            self._fwd_push.send_multipart(frames)
        elif isinstance(msg, Hello):
            self.hellos += 1
            self.log.info("renderer pid %d started (restart %d): both slabs free, next handoff full",
                          msg.pid, msg.restart_count)
            self._fwd_pull_drain()
            self.writer.reset_reader()
            self.frame_ema_ms = None
            self._recent_frames_ms.clear()
            self._frame_reports = 0
            self.done_seq = self.last_pub_seq
            if msg.gpu:
                self.on_gpu_info(msg.gpu)
        elif isinstance(msg, FrameTime):
            self._frame_reports += 1
            self._done(msg.seq)
            if msg.drawn:
                self.on_frame_time(msg.frame_ms)
        elif isinstance(msg, Idle):
            self._done(msg.last_seq)
            freed = self.writer.resync(msg.last_seq)
            if freed:
                self.resyncs += 1
                self.log.warning("renderer idle for %.0f ms holding no slab (newest handoff it got: %d): "
                                 "freed %d slab(s) whose release was lost", msg.idle_ms, msg.last_seq, freed)
            age = max(LOST_AFTER_S, self.stall_s)
            now = self.clock()
            lost = self.writer.free_lost(msg.last_seq, tuple(i for i in (0, 1) if now - self._sent_at[i] >= age))
            if lost:
                self.lost_handoffs += lost
                self.done_seq = self.last_pub_seq  # nothing is in flight: serve the next tick
                self.log.warning("renderer idle for %.0f ms and its newest handoff is %d, but %d later "
                                 "handoff(s) went %.0f s or more ago: lost on the way; freed, next handoff full",
                                 msg.idle_ms, msg.last_seq, lost, age)

    @property
    def stall_s(self) -> float:
        slowest = max(self._recent_frames_ms, default=0.0)
        return max(STALL_S, STALL_FRAMES * max(self.frame_ema_ms or 0.0, slowest) / 1000.0)

    def _done(self, seq: int) -> None:
        if seq > self.done_seq:
            self.done_seq = seq
            self._t_progress = self.clock()

    def _fwd_pull_drain(self) -> None:
        """Releases of the previous renderer still queued are stale after a hello."""
        while True:
            try:
                self._fwd_pull.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return

    def on_gpu_info(self, gpu: dict) -> None:
        """Re-resolve the policy with the renderer's adapter (tier detection + storage cap)."""
        base = self.decision.hardware or detect_hardware(probe_gpu=False)
        try:
            hw = HardwareInfo(cpu_cores=base.cpu_cores, memory_bytes=base.memory_bytes,
                              gpu_name=str(gpu.get("name") or "unknown"), gpu_type=str(gpu.get("type") or "Unknown"),
                              gpu_max_storage_binding=int(gpu["max_storage_binding"]) if gpu.get("max_storage_binding") else None,
                              gpu_max_buffer_size=int(gpu["max_buffer_size"]) if gpu.get("max_buffer_size") else None)
        except (TypeError, ValueError) as exc:
            self.bad_messages += 1
            self.log.warning("renderer hello: bad gpu info %r (%s); policy unchanged", gpu, exc)
            return
        old = self.decision
        self.decision = resolve_policy(self.cfg, hardware=hw)
        if (old.tier, old.point_budget) != (self.decision.tier, self.decision.point_budget):
            self.log.info("policy updated from the renderer's GPU %s: tier %s -> %s, budget %d -> %d",
                          hw.gpu_name, old.tier, self.decision.tier, old.point_budget, self.decision.point_budget)
        self.interval_ms = tick_interval_ms(self.cfg, self.decision, self.frame_ema_ms)
        self.ticker.set_interval(self.interval_ms / 1000.0)

    def on_frame_time(self, frame_ms: float) -> None:
        """Update the frame-time EMA (alpha 0.15) and, in adaptive mode, the tick interval."""
        ema = self.frame_ema_ms
        self.frame_ema_ms = frame_ms if ema is None else ema + FRAME_EMA_ALPHA * (frame_ms - ema)
        self._recent_frames_ms.append(frame_ms)
        if self.cfg.cadence.adaptive:
            ms = tick_interval_ms(self.cfg, self.decision, self.frame_ema_ms)
            if abs(ms - self.interval_ms) > 1e-6:
                self.interval_ms = ms
                self.ticker.set_interval(ms / 1000.0)

    # -------------------------------------------------------------- ticks
    def step(self, max_wait_s: float = 0.05):
        """Wait for the next tick (handling messages meanwhile) and serve it.

        Returns the :class:`Handoff` published, ``False`` for a skipped tick, ``None`` when
        ``max_wait_s`` ran out before the deadline."""
        tick = self.ticker.wait(idle=self.drain, max_wait_s=max_wait_s)
        if tick is None:
            return None
        return self.serve(tick)

    def serve(self, tick: Tick):
        self.ticks += 1
        self._late.append(tick.late_s)
        self._tick_times.append(tick.now)
        if tick.missed:
            self.skipped["late"] += tick.missed
        self.drain(0)
        if not self.renderer_heard:
            self.skipped["no_reader"] += 1
            self._prefill()
            return False
        if (self.latest_only and self.last_pub_seq > self.done_seq
                and self.clock() - self._t_progress < self.stall_s):
            self.skipped["renderer_pending"] += 1
            self._prefill()
            return False
        t0 = time.monotonic_ns()
        stats = self.writer.stats
        busy0, again0 = stats["skipped_busy"], stats["send_again"]
        h = self.writer.publish(extra={"budget": self.decision.point_budget, "interval_ms": self.interval_ms,
                                       "tick": tick.index})
        if h is None:
            if stats["send_again"] > again0:
                self.skipped["no_reader"] += 1
            elif stats["skipped_busy"] > busy0:
                self.skipped["renderer_busy"] += 1
            else:  # pragma: no cover - publish has no other None path today
                self.skipped["other"] += 1
            return False
        self.published += 1
        self.last_pub_seq = h.seq
        self._sent_at[h.slab] = self.clock()
        self._t_progress = self._t_copy = self.clock()
        self._pub_times.append(tick.now)
        if h.dirty is None:
            self.points_out += h.count
        else:
            self.points_out += sum(b - a for a, b in h.dirty)
        if self.spans is not None and h.trace_ids:
            t1 = h.t_snapshot_ns or time.monotonic_ns()
            for tid in h.trace_ids:
                self.spans.record(tid, "cadence_snapshot", t0, t1, 0)
        return h

    def _prefill(self) -> None:
        """Copy the ring's changes into the next slab ahead of its handoff (every PREFILL_S)."""
        now = self.clock()
        if now - self._t_copy >= PREFILL_S:
            self._t_copy = now
            self.writer.prefill()

    # -------------------------------------------------------------- stats
    def stats(self) -> dict[str, Any]:
        """Counters for ``ctx.counters.extra`` (rates over the last ~1000 ticks)."""
        late = np.asarray(self._late, dtype=np.float64) * 1000.0

        def rate(ts) -> float:
            return (len(ts) - 1) / (ts[-1] - ts[0]) if len(ts) > 1 and ts[-1] > ts[0] else 0.0

        w = self.writer.stats
        return {
            "target_hz": self.cfg.cadence.target_hz,
            "adaptive": self.cfg.cadence.adaptive,
            "interval_ms": round(self.interval_ms, 3),
            "ticks": self.ticks,
            "published": self.published,
            "skipped": dict(self.skipped),
            "achieved_hz": round(rate(self._tick_times), 3),
            "publish_hz": round(rate(self._pub_times), 3),
            "jitter_ms": {
                "p50": round(float(np.percentile(late, 50)), 4) if late.size else None,
                "p99": round(float(np.percentile(late, 99)), 4) if late.size else None,
                "max": round(float(late.max()), 4) if late.size else None,
            },
            "frame_ema_ms": None if self.frame_ema_ms is None else round(self.frame_ema_ms, 3),
            "budget": self.decision.point_budget,
            "full_copies": w["full_copies"],
            "copied_slots": w["copied_slots"],
            "prefilled_slots": w["prefilled_slots"],
            "renderer_hellos": self.hellos,
            "renderer_resyncs": self.resyncs,
            "lost_handoffs": self.lost_handoffs,
            "bad_messages": self.bad_messages,
        }

    def close(self) -> None:
        for s in (self._fwd_push, self._fwd_pull):
            s.close(0)


def main(ctx) -> None:
    """Stage entry point (``pointflow.cadence.process:main``)."""
    from ..ring import PointRing, SlabPair  # noqa: PLC0415

    cfg = ctx.cfg  # the run's PipelineConfig
    ring = PointRing.attach(ctx.info.ring_name)
    slabs = SlabPair.attach(ctx.info.slab_names)
    release = ctx.zmq.socket(zmq.PULL)
    release.setsockopt(zmq.LINGER, 0)
    release.bind(ctx.endpoints.release)
    ready = ctx.zmq.socket(zmq.PUSH)
    ready.setsockopt(zmq.LINGER, 0)
    ready.setsockopt(zmq.SNDHWM, 4)
    ready.setsockopt(zmq.IMMEDIATE, 1)  # never queue handoffs for a renderer that is not there
    ready.connect(ctx.endpoints.frames)
    # No GPU probe here: the renderer owns the adapter and reports its limits in its hello.
    decision = resolve_policy(cfg, probe_gpu=False)
    latest_only = cfg.cadence.latest_only
    # a restarted cadence serves the renderer that is already drawing at once (the renderer
    # says idle within 0.5 s anyway); the first one waits for the renderer's hello
    cad = Cadence(ring, slabs, ready, release, ctx.zmq, cfg, decision, spans=ctx.spans, log=ctx.log,
                  latest_only=latest_only, wait_for_renderer=not ctx.info.restart_count)
    if ctx.info.restart_count:
        ctx.log.info("cadence restarted (%d): resuming from the slab headers", ctx.info.restart_count)

    written0 = ring.stats().total_written

    def on_beat() -> None:
        # points_in: points committed to the ring while this cadence ran (what it could hand on)
        try:
            ctx.counters.points_in = max(0, ring.stats().total_written - written0)
        except RuntimeError:  # ring already detached during shutdown
            pass
        ctx.counters.points_out = cad.points_out
        ctx.counters.extra.update(cad.stats())
        ctx.counters.extra["policy"] = cad.decision.to_dict()

    ctx.on_beat.append(on_beat)
    try:
        while ctx.running:
            cad.step(max_wait_s=0.05)
            ctx.beat()
    finally:
        on_beat()
        cad.close()
        release.close(0)
        ready.close(0)
        slabs.close()
        ring.close()
