"""What every stage process shares: stop signals, heartbeats, counters, stats, spans.

The supervisor starts each stage with :func:`pointflow.runtime.stage.stage_main` in a fresh process.
The stage's own loop lives in a ``main(ctx: StageContext)`` function (its kind's
:attr:`~pointflow.stage.kinds.StageKind.main`, :mod:`pointflow.stage.kinds`) and must call ``ctx.beat()`` at least every ~100 ms and return
when ``ctx.running`` turns false.

Control messages (stage PUSH → supervisor PULL on ``endpoints.control``), JSON, one frame:
``{"type": "heartbeat", "stage", "pid", "t_ns", "stats": {...}}`` from the stage's loop,
``{"type": "pulse", "stage", "pid", "loop_age_ms"}`` from a side thread (liveness),
``{"type": "error", "stage", "pid", "message"}`` and ``{"type": "done", "stage", "pid"}``
(the stage ended on its own, e.g. a file source reached its end; with ``"stop_pipeline":
true`` and a ``reason`` it asks the supervisor to stop the whole run, e.g. the window closed),
``{"type": "fatal", "stage", "pid", "message"}`` (restarting cannot help, e.g. no input of a
file source can be read: the run fails with that message).
"""
from __future__ import annotations

import collections
import json
import logging
import os
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import zmq

from ..profiling.spans import SpanEmitter



@dataclass
class RunInfo:
    """What the supervisor hands a stage (picklable)."""

    run_dir: str
    #: the run's resolved :class:`pointflow.config.EndpointsConfig` (the kit sits below the
    #: config loader, which assembles the stages' sections, so it is not named here)
    endpoints: Any
    ring_name: str
    slab_names: tuple[str, str]
    out_dir: str | None
    supervisor_pid: int
    source_index: int = -1
    restart_count: int = 0
    log_level: int = logging.INFO
    extra: dict[str, Any] = field(default_factory=dict)
    #: The process that must stay the stage's parent: the supervisor (0), or the fork
    #: server that forked it (:mod:`.forkserver`); the stage stops when it goes.
    parent_pid: int = 0

    @property
    def parent(self) -> int:
        return self.parent_pid or self.supervisor_pid


class StageCounters:
    """Per-stage counts reported in heartbeats and in ``stats.json``."""

    def __init__(self) -> None:
        self.points_in = 0
        self.points_out = 0
        self.drops: collections.Counter[str] = collections.Counter()
        #: Free-form numbers (gauges, histograms summaries) the stage wants shown.
        self.extra: dict[str, Any] = {}

    def drop(self, reason: str, n: int = 1) -> None:
        if n:
            self.drops[reason] += int(n)

    def to_dict(self) -> dict[str, Any]:
        return {"points_in": self.points_in, "points_out": self.points_out,
                "drops": dict(self.drops), **self.extra}


class RateLimitedLog:
    """Logs the first defect of each reason, then a summary at most every ``every_s``."""

    def __init__(self, log: logging.Logger, every_s: float = 5.0):
        self.log = log
        self.every_s = every_s
        self._last: dict[str, float] = {}
        self._since: collections.Counter[str] = collections.Counter()

    def __call__(self, reason: str, message: str) -> None:
        now = time.monotonic()
        self._since[reason] += 1
        if now - self._last.get(reason, -1e9) >= self.every_s:
            n = self._since.pop(reason)
            self._last[reason] = now
            more = f" ({n - 1} more since last report)" if n > 1 else ""
            self.log.warning("rejected chunk [%s]: %s%s", reason, message, more)


def recv_frames(sock, flags: int = zmq.NOBLOCK) -> list:
    """One multipart message as ``zmq.Frame`` objects (raises ``zmq.Again`` when none waits).

    ``recv_multipart`` asks the socket for RCVMORE after every part (a getsockopt through
    pyzmq's option enum, ~1 us each); a received Frame already knows whether more follow.
    Frames rather than bytes: no copy of the data, and for the 1k-point chunks of a busy
    link about half the cost of ``recv_multipart(copy=True)`` (docs/ingest.md)."""
    recv = sock.recv
    f = recv(flags, copy=False)
    parts = [f]
    while f.more:
        f = recv(flags, copy=False)
        parts.append(f)
    return parts


def take_messages(sock, handle: Callable[[list], Any], limit: int) -> int:
    """Hand up to ``limit`` waiting messages (:func:`recv_frames`) to ``handle``, without
    waiting; returns how many there were."""
    got = 0
    for _ in range(limit):
        try:
            frames = recv_frames(sock)
        except zmq.Again:
            break
        handle(frames)
        got += 1
    return got


class StageContext:
    """One stage process's link to its supervisor; ``cfg`` is the run's
    :class:`pointflow.config.PipelineConfig`."""

    def __init__(self, name: str, kind: str, cfg: Any, info: RunInfo):
        self.name = name
        self.kind = kind
        self.cfg = cfg
        self.info = info
        self.endpoints = info.endpoints
        self.log = logging.getLogger(f"pointflow.{name}")
        self.counters = StageCounters()
        self.zmq = zmq.Context()
        self._running = True
        self._said_done = False  # input_ended() told the supervisor already
        self._hb_interval_ns = int(cfg.supervisor.heartbeat_ms * 1e6 / 2)
        self._last_hb = 0
        self._control = self.zmq.socket(zmq.PUSH)
        self._control.setsockopt(zmq.LINGER, 500)
        self._control.setsockopt(zmq.SNDHWM, 100)
        self._control.connect(info.endpoints.control)
        self.spans = SpanEmitter(self.zmq, info.endpoints.trace, name, cfg.tracing.batch,
                                 cfg.tracing.flush_ms, cfg.tracing.enabled)
        #: What a standby prepared before it was activated (:attr:`StageKind.prepare`), or None.
        self.prepared: Any = None
        #: Called with no arguments on each heartbeat; may add to ``counters.extra``.
        self.on_beat: list[Callable[[], None]] = []
        self._progress_ns = time.monotonic_ns()
        self._pulse_stop = threading.Event()
        self._pulse = threading.Thread(target=self._pulse_loop, name="pointflow-pulse", daemon=True)
        self._pulse.start()

    def _pulse_loop(self) -> None:
        """Liveness from a side thread, so a long frame (a software rasteriser drawing 1M
        points) is not mistaken for a hung process; the main loop's own progress is
        reported as ``loop_age_ms`` and judged against ``supervisor.stall_after_ms``."""
        sock = self.zmq.socket(zmq.PUSH)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.SNDHWM, 10)
        sock.connect(self.info.endpoints.control)
        period = self._hb_interval_ns / 1e9
        pid = os.getpid()
        try:
            while not self._pulse_stop.wait(period):
                age = (time.monotonic_ns() - self._progress_ns) / 1e6
                try:
                    sock.send_string(json.dumps({"type": "pulse", "stage": self.name, "pid": pid,
                                                 "loop_age_ms": round(age, 1)}), zmq.NOBLOCK)
                except zmq.Again:
                    pass
        finally:
            sock.close(0)

    @property
    def running(self) -> bool:
        if self._running and os.getppid() != self.info.parent:
            self.log.error("supervisor (pid %d) is gone; stopping", self.info.supervisor_pid)
            self._running = False
        return self._running

    def stop(self) -> None:
        self._running = False

    def beat(self, force: bool = False) -> None:
        now = time.monotonic_ns()
        self._progress_ns = now
        if not force and now - self._last_hb < self._hb_interval_ns:
            return
        self._last_hb = now
        for fn in self.on_beat:
            try:
                fn()
            except Exception:  # noqa: BLE001 - stats must not kill a stage
                self.log.exception("stats callback failed")
        self._send({"type": "heartbeat", "t_ns": now, "stats": self.counters.to_dict()})
        self.spans.maybe_flush()

    def input_ended(self) -> None:
        """Tell the supervisor this stage's input ran out (``finished`` in stats) while it
        stays up: a source keeps its socket connected until the pipeline stops it, because
        ZeroMQ drops what a receiver had not yet taken when the sending side disconnects."""
        if not self._said_done:
            self._said_done = True
            self.beat(force=True)  # the final counters first: "done" means they are all in
            self._send({"type": "done"})

    def request_stop(self, reason: str) -> None:
        """Ask the supervisor to stop the whole pipeline (e.g. the user closed the window)."""
        self._send({"type": "done", "stop_pipeline": True, "reason": reason})
        self._running = False

    def fail_run(self, message: str, error: dict | None = None) -> None:
        """End this stage and fail the whole run (exit 2) with ``message``: for defects a
        restart cannot cure (no input can be read). The supervisor prints it, once; the
        stage itself only when the message cannot reach the supervisor. ``error``: the
        error's fields (:func:`pointflow.errors.to_fields`), rebuilt in the parent."""
        if not self._send({"type": "fatal", "message": message[-4000:], "fields": error}):
            self.log.error("%s", message)
        self._running = False

    def report_error(self, message: str, error: dict | None = None) -> bool:
        """Hand an error (a traceback) to the supervisor, which prints it once with the
        stage's exit; ``error`` as at :meth:`fail_run`. False when it could not be sent."""
        return self._send({"type": "error", "message": message[-4000:], "fields": error})

    def _send(self, msg: dict) -> bool:
        msg.setdefault("stage", self.name)
        msg.setdefault("pid", os.getpid())
        try:
            self._control.send_string(json.dumps(msg, default=_json_default), zmq.NOBLOCK)
            return True
        except zmq.Again:
            return False

    def close(self) -> None:
        self._pulse_stop.set()
        self._pulse.join(1.0)
        try:
            self.beat(force=True)
            self.spans.close()
            self._control.close()
        finally:
            self.zmq.term()

    def drain_until_quiet(self, sock, take: Callable[[], Any], quiet_s: float, grace_s: float) -> None:
        """On stop (every stage gets SIGTERM in its wave): call ``take`` while ``sock`` has
        messages, until it was quiet for ``quiet_s`` (at most ``grace_s``), beating; so what
        the stages upstream sent before they exited is still taken and counted."""
        end = time.monotonic() + grace_s
        while time.monotonic() < end and sock.poll(int(quiet_s * 1000), zmq.POLLIN):
            take()
            self.beat()

    def sleep(self, seconds: float) -> None:
        """Sleep in small steps, beating, until ``seconds`` pass or a stop arrives."""
        end = time.monotonic() + seconds
        while self.running:
            left = end - time.monotonic()
            if left <= 0:
                return
            time.sleep(min(left, 0.05))
            self.beat()


def _json_default(o):
    try:
        import numpy as np

        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
    except ImportError:  # pragma: no cover
        pass
    return str(o)
