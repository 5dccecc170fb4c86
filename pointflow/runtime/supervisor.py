"""The supervisor: owns the shared memory, starts and watches the stage processes.

What a stage kind is (its loop, start order, stop wave, standby, counters, accounting)
is its record in :mod:`.kinds`; a role runs a list of kinds. Start order is downstream
first so every socket a stage connects to is already bound; stop order is upstream
first. Accounting is :mod:`.accounting`, hang judgement :mod:`.liveness`. Every stage
is its own OS process, a fresh interpreter started by :mod:`pointflow.runtime.launch`
(never a re-import of the caller's ``__main__``); the supervisor learns about them from
heartbeats on the control endpoint and from their exit codes, restarts a dead or hung
stage with backoff (up to ``supervisor.max_restarts``), and past that limit stops the
whole pipeline.

All of that runs in a background thread of the owning process (``pointflow-supervisor``),
started by :meth:`Supervisor.start`: restarts, heartbeats and :meth:`Supervisor.stats`
never wait for the caller to call ``poll()``/``wait()`` (a program with its own event loop,
or one that only sleeps, is supervised the same). The thread also starts and stops the
stages, because ``PR_SET_PDEATHSIG`` ties a stage to the *thread* that started it.
"""
from __future__ import annotations

import json
import logging
import os
import shutil
import threading
import time
from typing import Any, Optional

import zmq

from ..config import PipelineConfig, new_run_dir
from ..errors import Error, KeyedError, from_fields
from ..stage.accounting import RING_WRITER
from ..stage.context import RunInfo
from ..stage.kinds import StageKind, resolve, role_kinds, stage_kind
from .accounting import accounting, counter_names, merge_counts, reconcile_ring_writer
from .launch import spawn_stage
from .liveness import hang_reason
from .stagestate import StageProc, describe_exit

log = logging.getLogger("pointflow.supervisor")
#: The kind with one stage per configured source (and the ``api`` sources in this process).
SOURCE = "source"


def wanted_kinds(cfg: PipelineConfig, role: str) -> list[StageKind]:
    """The kinds ``role`` runs with ``cfg``, in start order. A kind's check of its config (an
    unwritable recording path) raises here, before anything starts."""
    return [k for k in role_kinds(role) if k.wanted is None or resolve(k.wanted)(cfg)]


def planned_stages(cfg: PipelineConfig, role: str = "pipeline") -> list[str]:
    """The stages a run of ``cfg`` has, in start order (every source that is not
    ``external``, the ``api`` ones included): what ``pointflow run`` says it is starting."""
    names: list[str] = []
    for k in wanted_kinds(cfg, role):
        if k.name == SOURCE:
            names.extend(s.name for s in cfg.sources if not s.external)
        else:
            names.append(k.name)
    return names


class PipelineFailed(Error, RuntimeError):
    """A stage kept failing past its restart limit (or failed the run); the pipeline was
    stopped. ``cause``: the stage's own keyed error (a :class:`~pointflow.errors.KeyedError`,
    e.g. a ``ConfigError`` with its ``key``), rebuilt from its fields; None otherwise."""

    def __init__(self, message: str, cause: Optional[KeyedError] = None):
        super().__init__(message)
        self.cause = cause

    def __reduce__(self):
        return (type(self), (str(self), self.cause))


#: A stage that ran this long before dying restarts with the first backoff again (a crash
#: an hour is not a crash loop), and no backoff is longer than BACKOFF_MAX_MS.
HEALTHY_S = 10.0
BACKOFF_MAX_MS = 10_000.0
#: How many standbys in a row may die before a stage's is given up (which kinds get one:
#: :attr:`StageKind.standby`).
STANDBY_MAX_FAILURES = 3
#: A standby is prepared only this long after the last stage reported in: preparing one
#: (the renderer's device and warm-up frame: 2-3 s of CPU on lavapipe) slows the frames of
#: a 2-core machine, and must not do so while frames resume after a restart.
STANDBY_DELAY_S = 5.0


class Supervisor:
    def __init__(self, cfg: PipelineConfig, out_dir: Optional[str] = None, role: str = "pipeline"):
        self.cfg = cfg
        #: "pipeline", "send" (``pointflow send``: the sources and the link sender, no ring)
        #: or "router" (``pointflow router``): the kinds it runs are :func:`.kinds.role_kinds`.
        self.role = role
        self.out_dir = out_dir
        self.stages: dict[str, StageProc] = {}
        #: The kinds this run has (its role's, as its config wants them), in start order.
        self.kinds: list[StageKind] = []
        self.uses_ring = False
        self.ring = None
        self.slabs = None
        self.run_dir: Optional[str] = None
        self.collector = None
        self.started = False
        self.failure: Optional[str] = None
        #: The failed stage's keyed error, rebuilt from its fields (PipelineFailed.cause).
        self.failure_cause: Optional[KeyedError] = None
        #: Set when a stage asked for the whole run to end (the window was closed).
        self.stop_requested: Optional[str] = None
        self.events: list[dict] = []   # restarts, failures, for stats
        self._zctx: Optional[zmq.Context] = None
        self._control: Optional[zmq.Socket] = None
        self._t_start = 0.0
        self._last_ps = 0.0
        #: Guards the stage table against the supervision thread (stats() from the caller).
        self._lock = threading.RLock()
        self._thread: Optional[threading.Thread] = None
        self._halt = threading.Event()      # set by stop(): the thread stops the stages and exits
        self._up = threading.Event()        # the thread started the stages (or failed to)
        self._reported = threading.Event()  # a stage reported in, failed or finished (wait_started)
        self._start_exc: Optional[BaseException] = None
        self._stop_timeout = 5.0
        self._shut = False
        self._forks = None  # the fork server of the first start (supervisor.fork_server)
        #: Where the start went before the stages: ``prepare`` (sweeps, the ring, the
        #: sockets) and ``fork_server`` (its imports, before the first fork), ms.
        self.startup_ms: dict[str, float] = {}
        self._t_call = 0.0

    # ------------------------------------------------------------------ start
    def start(self, wait: bool = True) -> None:
        """Create the ring and the run directory, spawn the stages; with ``wait``, return once
        they have reported in (:meth:`wait_started`), without, once they are spawned."""
        self._t_call = time.monotonic()
        from ..ring.config import check_ring_space
        from ..ring.sweep import sweep_orphans
        from .rundir import check_socket_paths, sweep_run_dirs

        cfg = self.cfg
        stale = sweep_orphans()
        if stale:
            log.warning("removed %d shared-memory segment(s) left by a pipeline that was killed: %s",
                        len(stale), ", ".join(stale))
        for d in sweep_run_dirs():
            log.warning("removed %s, the socket directory of a pipeline that was killed", d)
        self.kinds = wanted_kinds(cfg, self.role)
        self.uses_ring = any(k.name == RING_WRITER for k in self.kinds)  # no writer (send, router): no ring
        check_ring_space(cfg.ring, cfg.ring_channels())  # before anything is created
        self.run_dir = new_run_dir()
        self.endpoints = cfg.resolved_endpoints(self.run_dir)
        check_socket_paths(self.endpoints)  # the caller removes the run directory
        if self.out_dir:
            os.makedirs(self.out_dir, exist_ok=True)
        self._zctx = zmq.Context()
        self._control = self._zctx.socket(zmq.PULL)
        self._control.setsockopt(zmq.LINGER, 0)
        self._control.bind(self.endpoints.control)
        try:
            from ..profiling.collector import SpanCollector

            if cfg.tracing.enabled:
                self.collector = SpanCollector(self._zctx, self.endpoints.trace)
        except ImportError:
            self.collector = None
        if self.collector is None:  # keep the endpoint bound so stages never block on it
            self._trace_sink = self._zctx.socket(zmq.PULL)
            self._trace_sink.setsockopt(zmq.LINGER, 0)
            self._trace_sink.bind(self.endpoints.trace)
        self.segments = []
        if self.uses_ring:
            self._create_ring()
        self._add_stages()
        self._go(wait)

    def _create_ring(self) -> None:
        from ..ring.config import build_ring

        cfg = self.cfg
        self.ring, self.slabs = build_ring(cfg.ring, cfg.ring_channels(), check_space=False)  # checked in start()
        self.segments = [self.ring.name, *self.slabs.names]
        log.info("ring %s: %d points, channels %s, eviction %s; slabs %s", self.ring.name, cfg.ring.max_points,
                 cfg.ring_channels() or "[]", cfg.ring.eviction, " ".join(self.slabs.names))

    def _add_stages(self) -> None:
        """The stage table, in start order (downstream first): one stage per kind, one per
        configured source (not ``external``), and the ``api`` sources of this process."""
        from ..ingest.transports import runs_in_process

        for k in self.kinds:
            if k.name != SOURCE:
                self.stages[k.name] = StageProc(name=k.name, kind=k.name)
                continue
            for i, s in enumerate(self.cfg.sources):
                if not s.external and not runs_in_process(s.transport):
                    self.stages[s.name] = StageProc(name=s.name, kind=SOURCE, source_index=i)
        for s in self.cfg.sources:
            if not s.external and runs_in_process(s.transport):
                self.add_local_source(s.name, s.options)

    def add_local_source(self, name: str, options: Optional[dict] = None):
        """An ``api`` source in this process (declared, or added by ``Pipeline.send`` while
        the pipeline runs: nothing to start, so it is ready at once). Returns it."""
        from ..frames.deskew import time_fields
        from ..ingest.transports.api import ApiSource

        with self._lock:
            st = self.stages.get(name)
            if st is not None:
                if st.local is None:
                    what = "a source stage" if st.kind == SOURCE else f"the {st.kind} stage"
                    raise ValueError(f"source {name!r}: {name!r} is {what}, not an api source (Pipeline.send feeds "
                                     f"api sources; name one that is not a stage)")
                return st.local
            allowed = None if not self.uses_ring else self.cfg.ring_channels() + time_fields(self.cfg.frames)
            declared = next((s for s in self.cfg.sources if s.name == name), None)
            src = ApiSource(name, self.endpoints.ingest, options, channels=allowed,
                            max_chunk_points=self.cfg.ingest.max_chunk_points,
                            frame_id=declared.frame_id if declared is not None else None,
                            failed=lambda: None if self.failure is None else PipelineFailed(self.failure,
                                                                                           self.failure_cause))
            self.stages[name] = StageProc(name=name, kind=SOURCE, local=src, ready=True,
                                          started_ns=time.monotonic_ns(), pid=os.getpid())
            log.info("source %s: api source in this process (pid %d), fed by Pipeline.send; backpressure %s",
                     name, os.getpid(), src.o.backpressure)
            return src

    def _go(self, wait: bool = True) -> None:
        """Start the supervision thread; it starts the stages. With ``wait``, returns once
        every stage has reported in (:meth:`wait_started`); without, once they are spawned.
        Raises what starting the stages raised."""
        self._t_start = time.monotonic()
        self.started = True
        self._thread = threading.Thread(target=self._supervise, name="pointflow-supervisor", daemon=True)
        self._thread.start()
        self._up.wait()
        if self._start_exc is not None:
            raise self._start_exc
        if wait:
            self.wait_started()

    def starting(self) -> bool:
        """Still starting: some stage has not reported in (nor failed or finished), no stage
        failed the run, and ``supervisor.startup_timeout_ms`` has not passed since the start."""
        if not self.started or self.failure is not None or self._thread is None or not self._thread.is_alive():
            return False
        if time.monotonic() - self._t_start >= self.cfg.supervisor.startup_timeout_ms / 1000:
            return False
        with self._lock:
            return not all(st.ready or st.failed or st.finished for st in self.stages.values())

    def wait_started(self, timeout_s: Optional[float] = None) -> bool:
        """Wait until :meth:`starting` is over (every stage reported in, a failure, or the
        startup timeout: a busy machine can take seconds to start a few interpreters), or
        ``timeout_s``; so ``wait(5)`` afterwards is five seconds of a running pipeline. Woken
        by each stage's first heartbeat, not by a timer. True when it is over."""
        end = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            self._reported.clear()
            if not self.starting():
                return True
            left = self._t_start + self.cfg.supervisor.startup_timeout_ms / 1000 - time.monotonic()
            if end is not None:
                if end <= time.monotonic():
                    return False
                left = min(left, end - time.monotonic())
            self._reported.wait(max(0.0, min(left, 0.25)))  # 0.25: a thread that died sets nothing

    def _supervise(self) -> None:
        """The supervision thread: start the stages, watch them until stop(), stop them."""
        try:
            self._spawn_all()
        except BaseException as exc:  # noqa: BLE001 - handed to start()'s caller
            self._start_exc = exc
            self._up.set()
            self._shutdown(self._stop_timeout)
            return
        self._up.set()
        while not self._halt.is_set():
            try:
                self._poll_once(0.05)
            except Exception:  # noqa: BLE001 - supervision must go on
                log.exception("supervisor loop")
                self._halt.wait(0.05)
        self._shutdown(self._stop_timeout)

    def _spawn_all(self) -> None:
        """Start the stages in start order; after a kind that binds what a short replay must
        not miss (``await_ready``: the sender, which sources push to), wait for its first
        heartbeat before starting the next. With ``supervisor.fork_server`` and two stages or
        more they are forked from a fork server that imported their modules once
        (:mod:`.forkserver`; for one stage it would only add a process)."""
        t0 = time.monotonic()
        self.startup_ms["prepare"] = round((t0 - self._t_call) * 1000, 1)  # sweep, ring, sockets
        if self.cfg.supervisor.fork_server and sum(st.local is None for st in self.stages.values()) >= 2:
            from .forkserver import ForkServer

            try:
                self._forks = ForkServer(sorted({stage_kind(st.kind).main.partition(":")[0]
                                                 for st in self.stages.values() if st.local is None}),
                                         timeout_s=min(10.0, self.cfg.supervisor.startup_timeout_ms / 2000))
            except Exception as exc:  # noqa: BLE001 - no fork server is never a failed start
                log.warning("no fork server (%s): starting each stage as a new interpreter", exc)
                self._forks = None
            if self._forks is not None and not self._forks.ready:
                log.warning("the fork server did not start: starting each stage as a new interpreter")
                self._forks = None
            self.startup_ms["fork_server"] = round((time.monotonic() - t0) * 1000, 1)  # its imports
            self._t_start = time.monotonic()  # the startup window counts from the stages' start
        for st in list(self.stages.values()):
            if st.local is not None:
                continue
            self._spawn(st)
            if stage_kind(st.kind).await_ready:
                end = time.monotonic() + self.cfg.supervisor.startup_timeout_ms / 1000
                while (not st.ready and time.monotonic() < end and st.process.exitcode is None
                       and not self._halt.is_set()):
                    self._poll_once(0.05)

    def _run_info(self, st: StageProc, **extra) -> RunInfo:
        return RunInfo(
            run_dir=self.run_dir, endpoints=self.endpoints, ring_name=self.ring.name if self.ring else "",
            slab_names=tuple(self.slabs.names) if self.slabs else ("", ""), out_dir=self.out_dir,
            supervisor_pid=os.getpid(), source_index=st.source_index, restart_count=st.restarts,
            log_level=logging.getLogger("pointflow").getEffectiveLevel() or logging.INFO, extra=extra)

    def _spawn(self, st: StageProc) -> None:
        # a restarted renderer numbers its frames on from where the last one stopped
        info = self._run_info(st, frames_base=int((st.carried or {}).get("frames", 0)))
        t_spawn = time.monotonic_ns()  # before the process exists: its startup marks come after
        p = None
        if st.standby is not None:
            sb, st.standby = st.standby, None
            if sb.activate(info):
                p = sb
                log.info("%s: standby pid %d activated", st.name, p.pid)
            else:
                sb.kill()
                sb.join(1)
        if p is None and self._forks is not None and st.restarts == 0:  # the first start: forked
            p = self._forks.spawn(st.name, stage_kind(st.kind), self.cfg.to_dict(), self.cfg.base_dir, info)
        if p is None:
            p = spawn_stage(st.name, stage_kind(st.kind), self.cfg.to_dict(), self.cfg.base_dir, info)
        st.process, st.pid = p, p.pid
        st.dead = False
        st.started_ns = t_spawn
        st.last_seen_ns = st.last_progress_ns = time.monotonic_ns()
        st.restart_at_ns = 0
        st.ready = False
        st.ready_ns, st.marks = 0, {}
        st.watch(p.pid)
        log.debug("started %s (pid %d)", st.name, p.pid)

    # ------------------------------------------------------------------ watch
    def poll(self, timeout_s: float = 0.05) -> None:
        """Wait up to ``timeout_s``. Supervision runs in its own thread; this only does the
        work itself when called from that thread (or when there is none)."""
        if not self.started:
            return
        t = self._thread
        if t is not None and t.is_alive() and t is not threading.current_thread():
            self._halt.wait(timeout_s)
            return
        self._poll_once(timeout_s)

    def _poll_once(self, timeout_s: float) -> None:
        """Handle control messages and stage exits (the supervision thread's loop body)."""
        deadline = time.monotonic() + timeout_s
        while True:
            self._drain_control(max(0.0, deadline - time.monotonic()))
            if time.monotonic() >= deadline:
                break
        with self._lock:
            self._check_stages()
        now = time.monotonic()
        if now - self._last_ps >= 1.0:
            self._last_ps = now
            for st in list(self.stages.values()):
                st.sample()

    def _on_message(self, raw: bytes) -> None:
        try:
            msg = json.loads(raw)
            st = self.stages.get(msg.get("stage"))
        except (ValueError, AttributeError):
            log.warning("ignoring malformed control message")
            return
        if st is None or msg.get("pid") != st.pid or st.dead:
            return  # from an earlier incarnation
        now = time.monotonic_ns()
        st.last_seen_ns = now
        kind = msg.get("type")
        if kind == "starting":  # the stage's startup marks; it reports in with its first heartbeat
            marks = msg.get("marks_ns")
            if isinstance(marks, dict):
                st.marks = {k: v for k, v in marks.items() if isinstance(v, int)}
            return
        if kind == "pulse":
            if st.ready:
                age = msg.get("loop_age_ms", 0)
                st.last_progress_ns = now - int(age * 1e6) if isinstance(age, (int, float)) else st.last_progress_ns
            return
        if not st.ready:
            self._t_last_ready = time.monotonic()
            st.ready_ns = now
            self._reported.set()
        st.ready = True
        st.last_progress_ns = now
        if kind == "heartbeat":
            st.stats = msg.get("stats", {})
            seen = st.stats.get("ring_written_at_report")
            if st.kind == RING_WRITER and isinstance(seen, int):
                st.ring_at_report = seen
        elif kind == "fatal":  # restarting cannot help: the run fails
            st.last_error = str(msg.get("message", ""))
            st.last_error_fields = msg.get("fields")
            st.failed = True
            self.failure = f"stage {st.name}: {st.last_error}"
            self.failure_cause = from_fields(st.last_error_fields)
            self._reported.set()
            log.error("%s", self.failure)
            self.events.append({"stage": st.name, "pid": st.pid, "reason": st.last_error, "action": "stop",
                                "t": round(time.monotonic() - self._t_start, 3)})
        elif kind == "error":  # printed once, with the stage's exit (_stage_died: "last error: ...")
            st.last_error = msg.get("message", "")
            st.last_error_fields = msg.get("fields")
            log.debug("%s reported: %s", st.name, st.last_error)
        elif kind == "done":
            st.finished = True
            self._reported.set()
            if msg.get("stop_pipeline"):
                self.stop_requested = f"{st.name}: {msg.get('reason', 'asked to stop')}"
                log.info("stop requested by %s", self.stop_requested)
            else:
                log.info("%s finished (its input ended)", st.name)

    def _keep_standbys(self) -> None:
        """Start a standby for each render/cadence stage that has none, once every stage is
        running and STANDBY_DELAY_S after the last one reported in."""
        if not self.cfg.supervisor.standby or not self.uses_ring or self._halt.is_set():
            return
        if not all(st.ready or st.failed or st.finished for st in self.stages.values()):
            return
        if time.monotonic() - getattr(self, "_t_last_ready", 0.0) < STANDBY_DELAY_S:
            return
        for st in self.stages.values():
            if not stage_kind(st.kind).standby or st.failed or st.process is None:
                continue
            if st.standby is not None:
                if st.standby.exitcode is None:
                    continue
                st.standby_failures += 1
                log.warning("%s: standby pid %d %s", st.name, st.standby.pid, describe_exit(st.standby.exitcode))
                st.standby = None
            if st.standby_failures >= STANDBY_MAX_FAILURES:
                continue
            st.standby = spawn_stage(st.name, stage_kind(st.kind), self.cfg.to_dict(), self.cfg.base_dir,
                                     self._run_info(st), standby=True)
            log.debug("%s: standby pid %d started", st.name, st.standby.pid)
            return  # one at a time

    def _stop_standbys(self) -> None:
        for st in self.stages.values():
            sb, st.standby = st.standby, None
            if sb is not None:
                sb.kill()
                sb.join(2)

    def _check_stages(self) -> None:
        now = time.monotonic_ns()
        sup = self.cfg.supervisor
        self._keep_standbys()
        for st in self.stages.values():
            if st.failed or st.process is None:
                continue
            if st.restart_at_ns:
                if now >= st.restart_at_ns:
                    log.warning("restarting %s (restart %d of %d)", st.name, st.restarts, sup.max_restarts)
                    self._spawn(st)  # a new renderer announces itself to the cadence (hello)
                continue
            code = st.process.exitcode
            if code is not None:
                # take what it sent just before it ended (a source's "done", the last
                # heartbeat) before judging its exit
                self._drain_control(0.02)
            hung = hang_reason(st, now, sup, self.stages.values()) if code is None else None
            if code is None and hung is None:
                continue
            if code == 0 and st.finished and (st.kind == SOURCE or self.stop_requested):
                st.process.join(0)
                st.process = None  # its input ended: nothing to restart
                continue
            if hung is not None:
                reason = hung
                st.process.kill()
                st.process.join(2)
                if st.finished and st.kind == SOURCE:  # restarting would send its input again
                    log.warning("%s had said its input ended, then %s; killed, not restarted", st.name, hung)
                    st.process = None
                    continue
            else:
                reason = describe_exit(code)
            self._stage_died(st, reason)

    def _stage_died(self, st: StageProc, reason: str) -> None:
        sup = self.cfg.supervisor
        last = (st.last_error or "").strip().splitlines()
        detail = f"; last error: {last[-1]}" if last else ""
        if st.kind == RING_WRITER:
            reconcile_ring_writer(st, self.ring)
        st.carried = merge_counts(st.carried, st.stats)
        st.stats = {}
        st.dead = True
        ev = {"stage": st.name, "pid": st.pid, "reason": reason, "last_error": st.last_error,
              "t": round(time.monotonic() - self._t_start, 3)}
        if st.restarts >= sup.max_restarts:
            msg = f"stage {st.name} (pid {st.pid}) {reason}{detail}; restart limit {sup.max_restarts} reached, stopping the pipeline"
            log.error(msg)
            st.failed = True
            self.failure = msg
            self.failure_cause = from_fields(st.last_error_fields)
            self._reported.set()
            ev["action"] = "stop"
            self.events.append(ev)
            return
        st.restarts += 1
        lived_s = (time.monotonic_ns() - st.started_ns) / 1e9
        st.streak = 1 if (st.ready and lived_s >= HEALTHY_S) else st.streak + 1
        backoff = min(BACKOFF_MAX_MS, sup.restart_backoff_ms * (2 ** min(st.streak - 1, 30)))
        log.error("stage %s (pid %d) %s%s; restarting in %.0f ms", st.name, st.pid, reason, detail, backoff)
        st.restart_at_ns = time.monotonic_ns() + int(backoff * 1e6)
        st.last_error = None
        st.last_error_fields = None
        ev["action"] = "restart"
        ev["backoff_ms"] = backoff
        self.events.append(ev)

    # ------------------------------------------------------------------ stop
    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop upstream first: sources, then (once they are gone, so their last chunks are
        in ingest's socket) ingest, which drains before it exits, then cadence and render.
        The supervision thread does it (it started the stages) and exits; this waits."""
        if not self.started:
            return
        t = self._thread
        if t is not None and t.is_alive() and t is not threading.current_thread():
            self._stop_timeout = timeout_s
            self._halt.set()
            t.join()
        if not self._shut:  # no thread, or it died
            self._shutdown(timeout_s)

    def _shutdown(self, timeout_s: float) -> None:
        if self._shut:
            return
        self._shut = True
        self.started = False
        self._stop_standbys()
        for st in self.stages.values():  # api sources: what they accepted goes to ingest first
            if st.local is not None:
                try:
                    st.local.close()
                except Exception:  # noqa: BLE001
                    log.exception("closing api source %s", st.name)
        waves: dict[int, list[StageProc]] = {}
        for st in self.stages.values():
            waves.setdefault(stage_kind(st.kind).stop_wave, []).append(st)
        for _, wave in sorted(waves.items()):
            for st in wave:
                p = st.process
                if p is not None and p.exitcode is None:
                    try:
                        p.terminate()
                    except OSError:
                        pass
            # drain heartbeats while they exit, so the last counts are recorded
            deadline = time.monotonic() + timeout_s
            while time.monotonic() < deadline and any(
                    st.process is not None and st.process.exitcode is None for st in wave):
                self._drain_control(0.02)
            for st in wave:
                p = st.process
                if p is not None and p.exitcode is None:
                    log.warning("%s did not stop within %.1f s; killing it", st.name, timeout_s)
                    p.kill()
                    p.join(2)
        self._drain_control(0.1)
        if self._forks is not None:  # its stages are gone: it ends
            self._forks.close()
            self._forks = None
        with self._lock:
            ing = self.stages.get(RING_WRITER)
            if ing is not None:
                reconcile_ring_writer(ing, self.ring)
        self.final_stats = self.stats()
        with self._lock:
            self._release()

    def _drain_control(self, timeout_s: float) -> None:
        """Take the control messages that arrive within ``timeout_s``, and the spans."""
        if self._control is None:
            return
        if self._control.poll(int(timeout_s * 1000)):
            with self._lock:
                while True:
                    try:
                        self._on_message(self._control.recv(zmq.NOBLOCK))
                    except zmq.Again:
                        break
        if self.collector is not None:
            self.collector.poll(0)
        elif getattr(self, "_trace_sink", None) is not None:
            try:
                while True:
                    self._trace_sink.recv(zmq.NOBLOCK)
            except zmq.Again:
                pass

    def _release(self) -> None:
        """Unlink shared memory and sockets; safe to call twice."""
        for obj in (self.slabs, self.ring):
            if obj is None:
                continue
            try:
                obj.close()
            except Exception:  # noqa: BLE001
                log.exception("closing shared memory")
            try:
                obj.unlink()
            except FileNotFoundError:
                pass
            except Exception:  # noqa: BLE001
                log.exception("unlinking shared memory")
        self.slabs = None
        self.ring = None
        if self.collector is not None:
            self.collector.close()
        elif getattr(self, "_trace_sink", None) is not None:
            self._trace_sink.close()
        if self._control is not None:
            self._control.close()
            self._control = None
        if self._zctx is not None:
            self._zctx.term()
            self._zctx = None
        if self.run_dir:
            shutil.rmtree(self.run_dir, ignore_errors=True)

    # ------------------------------------------------------------------ stats
    def alive(self) -> bool:
        return self.started and self.failure is None and self.stop_requested is None

    def request(self, msg: dict, timeout_s: float = 10.0) -> dict:
        """Send a request to the render stage (REQ/REP on ``endpoints.render_commands``)."""
        if not self.started:
            raise RuntimeError("pipeline is not running")
        sock = self._zctx.socket(zmq.REQ)
        sock.setsockopt(zmq.LINGER, 0)
        try:
            sock.connect(self.endpoints.render_commands)
            sock.send_string(json.dumps(msg))
            if not sock.poll(int(timeout_s * 1000)):
                raise TimeoutError(f"render stage did not answer {msg.get('cmd')!r} within {timeout_s} s")
            return json.loads(sock.recv())
        finally:
            sock.close()

    def stats(self) -> dict[str, Any]:
        if not self.started and getattr(self, "final_stats", None):
            return self.final_stats
        with self._lock:
            return self._stats_locked()

    def _stats_locked(self) -> dict[str, Any]:
        stages = {}
        counters = counter_names()
        for st in self.stages.values():
            stages[st.name] = st.report(counters)
        out: dict[str, Any] = {
            "stages": stages,
            "frames": int(stages.get("render", {}).get("frames", 0)),
            "elapsed_s": round(time.monotonic() - self._t_start, 3) if self._t_start else 0.0,
            "events": list(self.events),
            "startup_ms": dict(self.startup_ms),
            "shm_segments": list(getattr(self, "segments", [])),
        }
        if self.ring is not None:
            try:  # never waits for a stage that holds the ring's lock (test_ring_lock_holder.py)
                out["ring"] = self.ring.stats(wait=False).to_dict()
            except Exception:  # noqa: BLE001
                pass
        elif getattr(self, "final_stats", None):
            out["ring"] = self.final_stats.get("ring")
        view = dict(stages)  # ingest's counts as of the ring's write count it last read
        if RING_WRITER in self.stages:
            view[RING_WRITER] = {**stages[RING_WRITER], "ring_written_at_report": self.stages[RING_WRITER].ring_at_report}
        out["accounting"] = accounting(self.kinds, view, out.get("ring"), self.cfg)
        if self.failure:
            out["failure"] = self.failure
        return out
