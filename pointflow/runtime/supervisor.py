"""The supervisor: owns the shared memory, starts and watches the stage processes.

Start order is downstream first (render, cadence, ingest, then sources) so every
socket a stage connects to is already bound. Stop order is upstream first. Every stage
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

import dataclasses
import json
import logging
import os
import shutil
import signal
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Optional

import psutil
import zmq

from ..config import ConfigError, PipelineConfig, new_run_dir
from .launch import StageProcess, spawn_stage
from .liveness import activity
from .stage import RunInfo

log = logging.getLogger("pointflow.supervisor")


class PipelineFailed(RuntimeError):
    """A stage kept failing past its restart limit; the pipeline was stopped."""


@dataclass
class StageProc:
    name: str
    kind: str
    source_index: int = -1
    process: Optional[StageProcess] = None
    pid: int = 0
    started_ns: int = 0
    last_seen_ns: int = 0      # any message (heartbeat or pulse)
    last_progress_ns: int = 0  # the stage's main loop last came round
    ready: bool = False        # has sent its first heartbeat
    restarts: int = 0
    stats: dict[str, Any] = field(default_factory=dict)
    last_error: Optional[str] = None
    finished: bool = False     # ended on its own (a source whose data ran out)
    failed: bool = False
    restart_at_ns: int = 0     # pending restart time (backoff), 0 = none
    psproc: Optional[psutil.Process] = None
    cpu_percent: float = 0.0
    rss_bytes: int = 0
    #: Counters of earlier incarnations, so totals survive a restart.
    carried: dict[str, Any] = field(default_factory=dict)
    #: Its death was recorded: late messages of that incarnation are ignored (their
    #: counts are in ``carried`` already).
    dead: bool = False
    #: Deaths in a row of incarnations that did not live HEALTHY_S: the backoff's exponent.
    streak: int = 0
    #: A prepared spare (``supervisor.standby``) that the next restart activates.
    standby: Optional[StageProcess] = None
    standby_failures: int = 0
    #: (when, what the kernel said, counted as starved) since the current silence was
    #: last found running (liveness.py).
    silence_mark: Optional[tuple] = None
    #: Silences past ``hung_after_ms`` that were starvation (the process ran or wanted to).
    starved: int = 0
    #: (start of the silence, main thread's CPU seconds when first watched, main thread
    #: never seen asleep since): a spin in a call that holds the GIL (liveness.py).
    busy_mark: Optional[tuple] = None
    #: Why the last silence was judged a hang, beyond the silence itself.
    hang_note: str = ""
    #: An ``api`` source living in this process (``Pipeline.send``): no process to watch,
    #: its counters read directly (pointflow/ingest/transports/api.py).
    local: Any = None
    #: Ingest only: the ring's write counter as of ingest's last report (read by ingest in
    #: the same instant as its counts) or as read back after it died (a new ring: 0).
    ring_at_report: int = 0


def _describe_exit(code: Optional[int]) -> str:
    if code is None:
        return "still running"
    if code < 0:
        try:
            return f"killed by signal {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exited with code {code}"


#: Stage stats that are running totals (carried over a restart); everything else is a
#: gauge and shows the current incarnation's value.
COUNTERS = ("points_in", "points_out", "frames", "pngs", "uploaded_bytes", "messages_in", "chunks_accepted",
            "transform_messages",
            "rejected_messages", "ring_evicted", "ring_pushes", "published", "chunks_out", "reconnects",
            # a link source (docs/remote.md): its ledger starts again in a restarted process
            "transport_link_sent", "transport_link_received", "transport_lost_in_transit",
            "transport_lost_chunks", "transport_joined_after",
            # a zenoh link source: arrived but dropped by its own bounded queue, dead senders
            "transport_receive_queue_full", "transport_receive_queue_full_chunks", "transport_senders_lost",
            # the recording (docs/record.md): ingest's copies for it, the recorder's files
            "record_offered", "record_sent", "record_dropped", "record_messages_sent", "record_bytes",
            "record_messages", "record_files",
            "record_transforms_sent", "record_transforms_dropped", "record_transforms",
            # `pointflow router` (docs/remote.md): connections over its restarts
            "sessions_opened", "sessions_closed", "refused_connections",
            # points a killed ingest wrote into the ring but never reported (reconciled from
            # the ring's own counter, see Supervisor._reconcile_ingest)
            "unreported_written")
COUNTER_MAPS = ("drops", "rejected", "skipped")


def _merge_counts(a: dict, b: dict) -> dict:
    """Totals of two incarnations' stats: counters added, per-reason maps merged."""
    out = dict(b)
    for k in COUNTERS:
        va, vb = a.get(k, 0), b.get(k, 0)
        if isinstance(va, (int, float)) and isinstance(vb, (int, float)) and (k in a or k in b):
            out[k] = va + vb
    for k in COUNTER_MAPS:
        if isinstance(a.get(k), dict) or isinstance(b.get(k), dict):
            m = dict(a.get(k) or {})
            for r, n in (b.get(k) or {}).items():
                m[r] = m.get(r, 0) + n if isinstance(n, (int, float)) else n
            out[k] = m
    return out


#: A stage that ran this long before dying restarts with the first backoff again (a crash
#: an hour is not a crash loop), and no backoff is longer than BACKOFF_MAX_MS.
HEALTHY_S = 10.0
BACKOFF_MAX_MS = 10_000.0
#: When several stages are silent at once, one counts as hung only after this many
#: times ``supervisor.hung_after_ms`` (at most ``stall_after_ms``).
STALLED_HUNG_FACTOR = 5
#: A stage that has not reported in within ``supervisor.startup_timeout_ms`` but is still
#: starting (using the CPU, or waiting for one) is kept up to this many times the timeout
#: (and at least ``supervisor.stall_after_ms``).
STARTUP_LOAD_FACTOR = 4

#: Stage kinds that get a standby, and how many standbys in a row may die before it is
#: given up. A render or cadence restart stops the frames until the new one draws; a fresh
#: source or ingest interpreter importing its modules slows the renderer of a 2-core
#: machine for seconds (the soak saw 2.1-2.7 s without a frame).
STANDBY_KINDS = ("render", "cadence", "ingest", "source")
STANDBY_MAX_FAILURES = 3
#: A standby is prepared only this long after the last stage reported in: preparing one
#: (the renderer's device and warm-up frame: 2-3 s of CPU on lavapipe) slows the frames of
#: a 2-core machine, and must not do so while frames resume after a restart.
STANDBY_DELAY_S = 5.0

#: sizeof(sockaddr_un.sun_path) - 1 on Linux: the longest ipc:// path ZeroMQ can bind.
IPC_PATH_MAX = 107


class Supervisor:
    def __init__(self, cfg: PipelineConfig, out_dir: Optional[str] = None, role: str = "pipeline"):
        self.cfg = cfg
        #: "pipeline", or "send": only the sources and the link sender (``pointflow send``,
        #: docs/remote.md), no ring, no shared memory.
        self.role = role
        self.out_dir = out_dir
        self.stages: dict[str, StageProc] = {}
        self.ring = None
        self.slabs = None
        self.run_dir: Optional[str] = None
        self.collector = None
        self.started = False
        self.failure: Optional[str] = None
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
        self._start_exc: Optional[BaseException] = None
        self._stop_timeout = 5.0
        self._shut = False

    # ------------------------------------------------------------------ start
    def start(self) -> None:
        from ..ring import PointRing, RingLayout, SlabPair
        from ..ring.layout import as_channel_specs
        from ..ring.space import RingSpaceError, check_shm_space, shm_bytes
        from ..ring.sweep import sweep_orphans
        from .rundir import sweep_run_dirs

        cfg = self.cfg
        stale = sweep_orphans()
        if stale:
            log.warning("removed %d shared-memory segment(s) left by a pipeline that was killed: %s",
                        len(stale), ", ".join(stale))
        for d in sweep_run_dirs():
            log.warning("removed %s, the socket directory of a pipeline that was killed", d)
        if cfg.record is not None and self.role != "send":  # an unwritable path: nothing started yet
            from ..record.config import prepare_record_path

            prepare_record_path(cfg.record)
        layout = RingLayout(cfg.ring.max_points, as_channel_specs(cfg.ring_channels()))
        try:  # before anything is created: nothing to clean up when it does not fit
            check_shm_space(layout)
        except RingSpaceError as exc:
            raise ConfigError("ring.max_points", str(exc)) from None
        self.run_dir = new_run_dir()
        self.endpoints = cfg.resolved_endpoints(self.run_dir)
        for key, ep in dataclasses.asdict(self.endpoints).items():
            sock = ep[len("ipc://"):] if isinstance(ep, str) and ep.startswith("ipc://") else ""
            if len(sock.encode()) > IPC_PATH_MAX:  # the caller removes the run directory
                raise ConfigError(f"endpoints.{key}", f"socket path {sock} has {len(sock.encode())} bytes, a Unix "
                                                      f"socket allows {IPC_PATH_MAX}; set XDG_RUNTIME_DIR (or the "
                                                      "endpoint) to a shorter path")
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
        if self.role == "router":  # `pointflow router`: one Zenoh router stage, no ring
            self.segments = []
            self.stages["router"] = StageProc(name="router", kind="router")
            self._go()
            return
        if self.role == "send":
            self.segments = []
            self.stages["sender"] = StageProc(name="sender", kind="sender")
            for i, s in enumerate(cfg.sources):
                if not s.external and not _in_process(s):
                    self.stages[s.name] = StageProc(name=s.name, kind="source", source_index=i)
            self._add_local_sources()
            self._go()
            return
        imp = "importance" if (cfg.ring.importance_field or cfg.ring.eviction == "importance") else None
        try:
            self.ring = PointRing(
                cfg.ring.max_points,
                channels=cfg.ring_channels(),
                eviction=cfg.ring.eviction,
                importance_field=imp,
                max_staleness_ms=cfg.ring.max_staleness_ms,
                classification_weights=cfg.ring.classification_weights,
            )
            self.slabs = SlabPair.create(self.ring.layout)
        except OSError as exc:  # space taken since the check, or a memory limit: the caller releases
            raise ConfigError("ring.max_points", f"cannot allocate the ring and slabs ({shm_bytes(layout):,} bytes) "
                                                 f"in shared memory: {exc.strerror or exc}") from None
        self.segments = [self.ring.name, *self.slabs.names]
        log.info("ring %s: %d points, channels %s, eviction %s; slabs %s", self.ring.name, cfg.ring.max_points,
                 cfg.ring_channels() or "[]", cfg.ring.eviction, " ".join(self.slabs.names))
        order = [("render", "render", -1), ("cadence", "cadence", -1), ("ingest", "ingest", -1)]
        if cfg.map is not None:  # the map stage (docs/map.md): after render, which binds what it connects to
            order.insert(1, ("map", "map", -1))
        if cfg.record is not None:  # binds the socket ingest sends its copies to: before ingest
            order.insert(2, ("recorder", "recorder", -1))
        order += [(s.name, "source", i) for i, s in enumerate(cfg.sources) if not s.external and not _in_process(s)]
        for name, kind, idx in order:
            self.stages[name] = StageProc(name=name, kind=kind, source_index=idx)
        self._add_local_sources()
        self._go()

    def _add_local_sources(self) -> None:
        for s in self.cfg.sources:
            if not s.external and _in_process(s):
                self.add_local_source(s.name, s.options)

    def add_local_source(self, name: str, options: Optional[dict] = None):
        """An ``api`` source in this process (declared, or added by ``Pipeline.send`` while
        the pipeline runs: nothing to start, so it is ready at once). Returns it."""
        from ..ingest.transports.api import ApiSource

        with self._lock:
            st = self.stages.get(name)
            if st is not None:
                if st.local is None:
                    raise ValueError(f"source {name!r} is a {st.kind} stage, not an api source")
                return st.local
            allowed = None if self.role == "send" else self.cfg.ring_channels() + _time_fields(self.cfg)
            declared = next((s for s in self.cfg.sources if s.name == name), None)
            src = ApiSource(name, self.endpoints.ingest, options, channels=allowed,
                            max_chunk_points=self.cfg.ingest.max_chunk_points,
                            frame_id=declared.frame_id if declared is not None else None)
            self.stages[name] = StageProc(name=name, kind="source", local=src, ready=True,
                                          started_ns=time.monotonic_ns(), pid=os.getpid())
            log.info("source %s: api source in this process (pid %d), fed by Pipeline.send; backpressure %s",
                     name, os.getpid(), src.o.backpressure)
            return src

    def _go(self) -> None:
        """Start the supervision thread; it starts the stages. Returns once every stage has
        reported in (a busy machine can take seconds to start a few interpreters), a stage
        failed past its restart limit, or ``supervisor.startup_timeout_ms`` passed; so
        ``wait(5)`` afterwards is five seconds of a running pipeline. Raises what starting
        the stages raised."""
        self._t_start = time.monotonic()
        self.started = True
        self._thread = threading.Thread(target=self._supervise, name="pointflow-supervisor", daemon=True)
        self._thread.start()
        self._up.wait()
        if self._start_exc is not None:
            raise self._start_exc
        end = time.monotonic() + self.cfg.supervisor.startup_timeout_ms / 1000
        while time.monotonic() < end and self.failure is None and self._thread.is_alive():
            with self._lock:
                if all(st.ready or st.failed or st.finished for st in self.stages.values()):
                    break
            time.sleep(0.02)

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
        if self.role == "send":
            # the sender binds the socket the sources push to: start it first and wait for
            # its first heartbeat, so a short replay is not over before anyone listens
            snd = self.stages["sender"]
            self._spawn(snd)
            end = time.monotonic() + self.cfg.supervisor.startup_timeout_ms / 1000
            while (not snd.ready and time.monotonic() < end and snd.process.exitcode is None
                   and not self._halt.is_set()):
                self._poll_once(0.05)
            for st in self.stages.values():
                if st is not snd and st.local is None:
                    self._spawn(st)
            return
        for st in self.stages.values():
            if st.local is None:
                self._spawn(st)

    def _spawn(self, st: StageProc) -> None:
        info = RunInfo(
            run_dir=self.run_dir, endpoints=self.endpoints, ring_name=self.ring.name if self.ring else "",
            slab_names=tuple(self.slabs.names) if self.slabs else ("", ""), out_dir=self.out_dir,
            supervisor_pid=os.getpid(),
            source_index=st.source_index, restart_count=st.restarts,
            log_level=logging.getLogger("pointflow").getEffectiveLevel() or logging.INFO,
            # a restarted renderer numbers its frames on from where the last one stopped
            extra={"frames_base": int((st.carried or {}).get("frames", 0))},
        )
        p = None
        if st.standby is not None:
            sb, st.standby = st.standby, None
            if sb.activate(info):
                p = sb
                log.info("%s: standby pid %d activated", st.name, p.pid)
            else:
                sb.kill()
                sb.join(1)
        if p is None:
            p = spawn_stage(st.name, st.kind, self.cfg.to_dict(), self.cfg.base_dir, info)
        st.process, st.pid = p, p.pid
        st.dead = False
        st.started_ns = st.last_seen_ns = st.last_progress_ns = time.monotonic_ns()
        st.restart_at_ns = 0
        st.ready = False
        try:
            st.psproc = psutil.Process(p.pid)
            st.psproc.cpu_percent(None)
        except psutil.Error:
            st.psproc = None
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
            left = max(0.0, deadline - time.monotonic())
            if self._control.poll(int(left * 1000)):
                with self._lock:
                    while True:
                        try:
                            raw = self._control.recv(zmq.NOBLOCK)
                        except zmq.Again:
                            break
                        self._on_message(raw)
            if self.collector is not None:
                self.collector.poll(0)
            else:
                try:
                    while True:
                        self._trace_sink.recv(zmq.NOBLOCK)
                except zmq.Again:
                    pass
            if time.monotonic() >= deadline:
                break
        with self._lock:
            self._check_stages()
        now = time.monotonic()
        if now - self._last_ps >= 1.0:
            self._last_ps = now
            for st in list(self.stages.values()):
                if st.psproc is not None:
                    try:
                        st.cpu_percent = st.psproc.cpu_percent(None)
                        st.rss_bytes = st.psproc.memory_info().rss
                    except psutil.Error:
                        pass

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
        if kind == "pulse":
            if st.ready:
                age = msg.get("loop_age_ms", 0)
                st.last_progress_ns = now - int(age * 1e6) if isinstance(age, (int, float)) else st.last_progress_ns
            return
        if not st.ready:
            self._t_last_ready = time.monotonic()
        st.ready = True
        st.last_progress_ns = now
        if kind == "heartbeat":
            st.stats = msg.get("stats", {})
            seen = st.stats.get("ring_written_at_report")
            if st.kind == "ingest" and isinstance(seen, int):
                st.ring_at_report = seen
        elif kind == "fatal":  # restarting cannot help: the run fails
            st.last_error = str(msg.get("message", ""))
            st.failed = True
            self.failure = f"stage {st.name}: {st.last_error}"
            log.error("%s", self.failure)
            self.events.append({"stage": st.name, "pid": st.pid, "reason": st.last_error, "action": "stop",
                                "t": round(time.monotonic() - self._t_start, 3)})
        elif kind == "error":  # printed once, with the stage's exit (_stage_died: "last error: ...")
            st.last_error = msg.get("message", "")
            log.debug("%s reported: %s", st.name, st.last_error)
        elif kind == "done":
            st.finished = True
            if msg.get("stop_pipeline"):
                self.stop_requested = f"{st.name}: {msg.get('reason', 'asked to stop')}"
                log.info("stop requested by %s", self.stop_requested)
            else:
                log.info("%s finished (its input ended)", st.name)

    def _keep_standbys(self) -> None:
        """Start a standby for each render/cadence stage that has none, once every stage is
        running and STANDBY_DELAY_S after the last one reported in."""
        if not self.cfg.supervisor.standby or self.role == "send" or self._halt.is_set():
            return
        if not all(st.ready or st.failed or st.finished for st in self.stages.values()):
            return
        if time.monotonic() - getattr(self, "_t_last_ready", 0.0) < STANDBY_DELAY_S:
            return
        for st in self.stages.values():
            if st.kind not in STANDBY_KINDS or st.failed or st.process is None:
                continue
            if st.standby is not None:
                if st.standby.exitcode is None:
                    continue
                st.standby_failures += 1
                log.warning("%s: standby pid %d %s", st.name, st.standby.pid, _describe_exit(st.standby.exitcode))
                st.standby = None
            if st.standby_failures >= STANDBY_MAX_FAILURES:
                continue
            info = RunInfo(run_dir=self.run_dir, endpoints=self.endpoints, ring_name=self.ring.name,
                           slab_names=tuple(self.slabs.names), out_dir=self.out_dir, supervisor_pid=os.getpid(),
                           source_index=st.source_index, restart_count=st.restarts,
                           log_level=logging.getLogger("pointflow").getEffectiveLevel() or logging.INFO)
            st.standby = spawn_stage(st.name, st.kind, self.cfg.to_dict(), self.cfg.base_dir, info, standby=True)
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
                    self._spawn(st)
                    self._notify_restart(st)
                continue
            code = st.process.exitcode
            if code is not None:
                # take what it sent just before it ended (a source's "done", the last
                # heartbeat) before judging its exit
                self._drain_control(0.02)
            limit_ms = sup.hung_after_ms if st.ready else sup.startup_timeout_ms
            silent = (now - st.last_seen_ns) > limit_ms * 1e6
            if silent and st.ready and code is None:
                silent = self._silence_is_hang(st, now, limit_ms)
            elif silent and code is None:
                silent = self._start_is_stuck(st, now, limit_ms)
            stalled = st.ready and (now - st.last_progress_ns) > sup.stall_after_ms * 1e6
            hung = code is None and (silent or stalled)
            if code is None and not hung:
                continue
            if code == 0 and st.finished and (st.kind == "source" or self.stop_requested):
                st.process.join(0)
                st.process = None  # its input ended: nothing to restart
                continue
            if hung:
                if not st.ready:
                    reason = f"did not start: no heartbeat within {(now - st.started_ns) / 1e6:.0f} ms"
                elif silent:
                    reason = f"hung: no heartbeat for {(now - st.last_seen_ns) / 1e6:.0f} ms{st.hang_note}"
                else:
                    reason = f"stuck: its loop has not come round for {(now - st.last_progress_ns) / 1e6:.0f} ms"
                st.process.kill()
                st.process.join(2)
            else:
                reason = _describe_exit(code)
            self._stage_died(st, reason)

    def _silence_is_hang(self, st: StageProc, now: int, limit_ms: float) -> bool:
        """A stage silent for ``limit_ms``: hung, or starved of CPU on a loaded machine?
        The kernel says (:mod:`.liveness`). Starved (a thread waiting to run or for the
        disk, or CPU time used since the silence began): not hung, however long, up to
        ``stall_after_ms``. Frozen (SIGSTOP): hung now. Asleep without using any CPU for
        half of ``limit_ms`` (at least 250 ms) of watching: hung (a deadlock). The last two
        only when the other stages talk, or after a longer silence when they do not (the
        machine, or this process, stalled)."""
        sup = self.cfg.supervisor
        quiet = now - st.last_seen_ns
        if quiet > sup.stall_after_ms * 1e6:
            return True
        act = activity(st.pid)
        if act is None:
            return False  # it ended: its exit code tells why, next round
        st.hang_note = ""
        if self._spins_holding_the_gil(st, act):
            return True
        mark = st.silence_mark
        if mark is None or mark[0] < st.last_seen_ns:  # this silence just began
            st.silence_mark = (now, act, False)
            if not act.stopped:
                return False
        else:
            t0, before, counted = mark
            if act.running_since(before, (now - t0) / 1e9):  # starved, not hung: watch afresh
                if not counted:
                    st.starved += 1
                st.silence_mark = (now, act, True)
                return False
            if not act.stopped and now - t0 < max(limit_ms * 1e6 / 2, 250e6):
                return False  # asleep, not watched long enough yet
        if self._silent_alone(st, limit_ms):
            return True
        # others went quiet too: the machine (or this process) stalled; only a longer
        # silence counts then
        return quiet > max(limit_ms, min(sup.stall_after_ms, STALLED_HUNG_FACTOR * limit_ms)) * 1e6

    def _start_is_stuck(self, st: StageProc, now: int, limit_ms: float) -> bool:
        """Not reported in within ``startup_timeout_ms``: stuck, or still starting on a
        loaded machine? A fresh interpreter importing numpy, ZeroMQ and wgpu took 13-32 s to
        start a pipeline at load 14-18 on 2 cores; killing it there only starts the same
        work again. Still starting (it used at least 2% of a CPU since the last look, or a
        thread waits for one): kept, up to ``STARTUP_LOAD_FACTOR`` x the timeout (at least
        ``stall_after_ms``). Frozen (SIGSTOP), or asleep without using the CPU for a second
        of watching: did not start."""
        if now - st.started_ns > max(STARTUP_LOAD_FACTOR * limit_ms, self.cfg.supervisor.stall_after_ms) * 1e6:
            return True
        act = activity(st.pid)
        if act is None:
            return False  # it ended: its exit code tells why, next round
        if act.stopped:
            return True
        mark = st.silence_mark
        if mark is None or mark[0] < st.started_ns:  # first look past the timeout
            st.silence_mark = (now, act, False)
            return False
        t0, before, _ = mark
        if act.running_since(before, (now - t0) / 1e9):
            st.silence_mark = (now, act, True)
            return False
        return now - t0 >= 1e9

    def _spins_holding_the_gil(self, st: StageProc, act) -> bool:
        """Silent, yet its main thread has been on (or waiting for) a CPU at every look and
        used ``stuck_cpu_ms`` of CPU: it spins in a call that holds the GIL, so its pulse
        thread cannot talk. Counted in CPU time, not wall time, so load does not trigger it;
        a starved stage's main thread gets little CPU, and a healthy one sleeps (and lets
        the pulse through) long before."""
        mark = st.busy_mark
        if mark is None or mark[0] != st.last_seen_ns:
            st.busy_mark = (st.last_seen_ns, act.main_cpu_s, act.main_awake)
            return False
        awake = mark[2] and act.main_awake
        st.busy_mark = (mark[0], mark[1], awake)
        used_s = act.main_cpu_s - mark[1]
        if awake and used_s * 1000.0 >= self.cfg.supervisor.stuck_cpu_ms:
            st.hang_note = (f"; its main thread ran {used_s:.1f} s of CPU and never slept: "
                            "stuck in a call that holds the GIL")
            return True
        return False

    def _silent_alone(self, st: StageProc, limit_ms: float) -> bool:
        """True when every other live stage was heard from within the last half
        ``limit_ms``: the rest of the pipeline is running while ``st`` is not (a frozen or
        hung process). When several stages went silent together, the machine (or this
        process) stalled: at load 15-20 on 2 cores three healthy stages went quiet for
        0.9-1.9 s at once while the fourth still talked, and killing them only made it
        worse."""
        now = time.monotonic_ns()
        others = [o.last_seen_ns for o in self.stages.values()
                  if o is not st and o.ready and not o.dead and o.process is not None and o.process.exitcode is None]
        return all(now - t <= limit_ms * 1e6 / 2 for t in others)

    def _stage_died(self, st: StageProc, reason: str) -> None:
        sup = self.cfg.supervisor
        last = (st.last_error or "").strip().splitlines()
        detail = f"; last error: {last[-1]}" if last else ""
        if st.kind == "ingest":
            self._reconcile_ingest(st)
        st.carried = _merge_counts(st.carried, st.stats)
        st.stats = {}
        st.dead = True
        ev = {"stage": st.name, "pid": st.pid, "reason": reason, "last_error": st.last_error,
              "t": round(time.monotonic() - self._t_start, 3)}
        if st.restarts >= sup.max_restarts:
            msg = f"stage {st.name} (pid {st.pid}) {reason}{detail}; restart limit {sup.max_restarts} reached, stopping the pipeline"
            log.error(msg)
            st.failed = True
            self.failure = msg
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
        ev["action"] = "restart"
        ev["backoff_ms"] = backoff
        self.events.append(ev)

    def _reconcile_ingest(self, st: StageProc) -> None:
        """Points an ingest wrote after its last heartbeat (killed, or its last report lost)
        are in the ring but not in its counters. The ring's own write count (in shared
        memory, updated under the ring's lock in the same step as the write) is the truth:
        add the difference to the counts (received and written) and report it as
        ``unreported_written``. Runs when ingest dies and once more after the stop."""
        if self.ring is None:
            return
        try:
            # without the ring's lock: a stage stopped inside a push (frozen, starved) must
            # not stop supervision; the writer is gone, so the counter is final
            written = int(self.ring.stats(wait=False).total_written)
        except Exception:  # noqa: BLE001
            return
        st.ring_at_report = written  # both sides as of now: ingest's totals are set from it
        reported = int(st.carried.get("points_out", 0)) + int(st.stats.get("points_out", 0))
        if written > reported:
            st.stats = dict(st.stats)
            for k in ("points_in", "points_out", "unreported_written"):
                st.stats[k] = int(st.stats.get(k, 0)) + (written - reported)
            log.info("ingest: %d points written after its last report added to its counts", written - reported)

    def _notify_restart(self, st: StageProc) -> None:
        """A new renderer holds no slab: the cadence must consider both free."""
        # The render stage announces itself to the cadence on the release socket when
        # it starts; nothing else to do here. Kept as a hook for stages that need it.

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
        sources = [st for st in self.stages.values() if st.kind == "source"]
        waves = [sources, [self.stages[n] for n in ("ingest", "sender", "router") if n in self.stages],
                 [self.stages[n] for n in ("cadence", "render", "recorder", "map") if n in self.stages]]
        for wave in waves:
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
        with self._lock:
            ing = self.stages.get("ingest")
            if ing is not None:
                self._reconcile_ingest(ing)
        self.final_stats = self.stats()
        with self._lock:
            self._release()

    def _drain_control(self, timeout_s: float) -> None:
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
        for st in self.stages.values():
            if st.local is not None:
                st.stats = st.local.stats()
            d = _merge_counts(st.carried, st.stats) if st.carried else dict(st.stats)
            d.setdefault("points_in", 0)
            d.setdefault("points_out", 0)
            d.setdefault("drops", {})
            d.update(pid=st.pid, kind=st.kind, cpu_percent=round(st.cpu_percent, 1), rss_bytes=st.rss_bytes,
                     restarts=st.restarts, alive=bool(st.process is not None and st.process.exitcode is None)
                     or bool(st.local is not None and not st.local.closed),
                     ready=st.ready,  # this incarnation has reported in
                     standby_pid=st.standby.pid if st.standby is not None else None,
                     starved_silences=st.starved,  # silent past hung_after_ms, but running: kept
                     finished=st.finished)
            if st.last_error:
                d["last_error"] = st.last_error[-2000:]
            stages[st.name] = d
        out: dict[str, Any] = {
            "stages": stages,
            "frames": int(stages.get("render", {}).get("frames", 0)),
            "elapsed_s": round(time.monotonic() - self._t_start, 3) if self._t_start else 0.0,
            "events": list(self.events),
            "shm_segments": list(getattr(self, "segments", [])),
        }
        if self.ring is not None:
            try:  # never waits for a stage that holds the ring's lock (test_ring_lock_holder.py)
                out["ring"] = self.ring.stats(wait=False).to_dict()
            except Exception:  # noqa: BLE001
                pass
        elif getattr(self, "final_stats", None):
            out["ring"] = self.final_stats.get("ring")
        out["accounting"] = self._accounting(stages, out.get("ring"))
        if self.failure:
            out["failure"] = self.failure
        return out

    def _accounting(self, stages: dict, ring: Optional[dict]) -> dict[str, Any]:
        """Where every point went: ingest's balance (points of accepted chunks = written +
        dropped by reason; rejected messages are counted per message and reason),
        the ring agreeing with ingest, and points the sources sent that ingest never saw
        (lost in the socket buffers of a killed ingest; known only without external sources and
        while no source was killed, since a killed source's last counts die with it)."""
        if self.role == "send":
            return self._send_accounting(stages)
        if self.role == "router":
            return {}
        ing = stages.get("ingest", {})
        rejected = ing.get("rejected", {})
        acc: dict[str, Any] = {
            "ingest_received": ing.get("points_in", 0),
            "ingest_written": ing.get("points_out", 0),
            "ingest_dropped": sum(ing.get("drops", {}).values()),
            "ingest_rejected_messages": sum(v for v in rejected.values() if isinstance(v, (int, float)))
            if isinstance(rejected, dict) else 0,
        }
        acc["ingest_balanced"] = acc["ingest_received"] == acc["ingest_written"] + acc["ingest_dropped"]
        # written by an ingest that died before reporting them, read back from the ring
        acc["ingest_unreported_written"] = ing.get("unreported_written", 0)
        if ring:
            # As of ingest's last report (the ring's counter read by ingest with its counts),
            # or as read back after it died or the run stopped: then both sides hold the same
            # writes. The counter now runs ahead of any report while ingest writes (the pushes
            # since its last heartbeat); comparing it with the report read ring_agrees: false
            # in live samples under load (issue 31).
            now_written = ring.get("total_written")
            ing_st = self.stages.get("ingest")
            acc["ring_written"] = ing_st.ring_at_report if ing_st is not None else now_written
            acc["ring_written_now"] = now_written
            acc["ring_agrees"] = acc["ring_written"] == acc["ingest_written"]
        sources = [v for v in stages.values() if v.get("kind") == "source"]
        acc.update(_source_balance(sources))
        if not any(s.external for s in self.cfg.sources):
            acc["sources_sent"] = sum(v.get("points_out", 0) for v in sources)
            if any(v.get("restarts") for v in sources):
                # a killed source's sends since its last heartbeat died with it
                acc["lost_before_ingest"] = None
            else:
                acc["lost_before_ingest"] = acc["sources_sent"] - acc["ingest_received"]
        if "recorder" in stages:
            acc.update(self._record_accounting(ing, stages["recorder"]))
        if "map" in stages:  # the map layer (docs/map.md)
            from ..map.stage import accounting as map_accounting

            acc.update(map_accounting(stages, self.ring))
        link = [v for v in sources if "transport_link_sent" in v]
        if link:
            # zmq sources fed by `pointflow send` (docs/remote.md): what the senders sent
            # since this pipeline joined = what arrived + what the link lost
            acc["link_sent"] = sum(v.get("transport_link_sent", 0) for v in link)
            acc["link_received"] = sum(v.get("transport_link_received", 0) for v in link)
            acc["lost_in_transit"] = sum(v.get("transport_lost_in_transit", 0) for v in link)
            acc["lost_in_transit_by_source"] = {k.split(":", 1)[1]: n for v in link for k, n in v.items()
                                                if k.startswith("transport_lost_in_transit:")}
            # a zenoh source's own bounded queue (docs/remote.md, "The Zenoh engine")
            dropped = [v["transport_receive_queue_full"] for v in link if "transport_receive_queue_full" in v]
            if dropped:
                acc["receive_queue_full"] = sum(dropped)
            acc["link_balanced"] = acc["link_sent"] == acc["link_received"] + acc["lost_in_transit"] \
                + acc.get("receive_queue_full", 0)
        return acc

    def _record_accounting(self, ing: dict, rec: dict) -> dict[str, Any]:
        """The recording (docs/record.md): ingest offers the recorder each chunk it pushes to
        the ring, sends it or drops it (never waits); the recorder writes what it received or
        drops it (disk full); what was sent but never received died in a killed recorder's
        socket (``lost_before_recorder``, 0 on a clean stop)."""
        drops = ing.get("drops", {})
        acc: dict[str, Any] = {
            "record_offered": ing.get("record_offered", 0),
            "record_sent": ing.get("record_sent", 0),
            "record_dropped": ing.get("record_dropped", 0),
            "recorder_received": rec.get("points_in", 0),
            "recorder_written": rec.get("points_out", 0),
            "recorder_dropped": sum(rec.get("drops", {}).values()),
        }
        # what ingest offered is what it handed the ring: written, or refused by the ring
        acc["record_covers_ring"] = acc["record_offered"] == (
            ing.get("points_out", 0) + drops.get("out_of_range", 0) + drops.get("ring_full", 0)) \
            if not ing.get("restarts") else None  # a killed ingest's points_out is taken from the ring
        acc["record_tap_balanced"] = acc["record_offered"] == acc["record_sent"] + acc["record_dropped"]
        acc["recorder_balanced"] = acc["recorder_received"] == acc["recorder_written"] + acc["recorder_dropped"]
        # a killed ingest's or recorder's counts since its last heartbeat died with it
        acc["lost_before_recorder"] = acc["record_sent"] - acc["recorder_received"] \
            if not (ing.get("restarts") or rec.get("restarts")) else None
        return acc

    def _send_accounting(self, stages: dict) -> dict[str, Any]:
        """``pointflow send``: points the sources produced = handed to the link + dropped."""
        snd = stages.get("sender", {})
        sources = [v for v in stages.values() if v.get("kind") == "source"]
        acc: dict[str, Any] = {
            **_source_balance(sources),
            "sources_sent": sum(v.get("points_out", 0) for v in sources),
            "sender_received": snd.get("points_in", 0),
            "link_sent": snd.get("points_out", 0),
            "sender_dropped": sum(snd.get("drops", {}).values()),
            "sender_queued": snd.get("queued_points", 0),
        }
        acc["sender_balanced"] = acc["sender_received"] == acc["link_sent"] + acc["sender_dropped"] + acc["sender_queued"]
        if not any(v.get("restarts") for v in sources):
            acc["lost_before_sender"] = acc["sources_sent"] - acc["sender_received"]
        return acc


def _in_process(s) -> bool:
    """A source the supervisor keeps in its own process (``transport: api``)."""
    if s.transport == "api":
        return True
    try:
        from ..ingest.transports import resolve_transport

        return bool(getattr(resolve_transport(s.transport), "in_process", False))
    except Exception:  # noqa: BLE001 - the config loader already checked it resolves
        return False


def _time_fields(cfg) -> list[str]:
    """Per-point time fields ingest's deskew reads (kept whatever the ring holds)."""
    fcfg = cfg.frames
    if not fcfg.fixed or fcfg.deskew == "off":
        return []
    from ..frames.deskew import TIME_FIELDS

    return [fcfg.deskew.field] if not isinstance(fcfg.deskew, str) else list(TIME_FIELDS)


def _source_balance(sources: list[dict]) -> dict[str, Any]:
    """The sources' own balance: points their transports produced = sent on to ingest (or
    the sender) + dropped there by reason (``hwm``: the send queue stayed full, e.g. a link
    delivering faster than ingest takes; ``encode_error``)."""
    by_reason: dict[str, int] = {}
    for v in sources:
        for r, n in (v.get("drops") or {}).items():
            by_reason[r] = by_reason.get(r, 0) + n
    out: dict[str, Any] = {
        "sources_received": sum(v.get("points_in", 0) for v in sources),
        "sources_forwarded": sum(v.get("points_out", 0) for v in sources),
        "sources_dropped": sum(by_reason.values()),
        "sources_dropped_by_reason": by_reason,
    }
    out["sources_balanced"] = out["sources_received"] == out["sources_forwarded"] + out["sources_dropped"]
    return out
