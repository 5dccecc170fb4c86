"""The supervisor: owns the shared memory, starts and watches the stage processes.

Start order is downstream first (render, cadence, ingest, then sources) so every
socket a stage connects to is already bound. Stop order is upstream first. Every stage
is a ``spawn``-ed OS process; the supervisor learns about them from heartbeats on the
control endpoint and from their exit codes, restarts a dead or hung stage with backoff
(up to ``supervisor.max_restarts``), and past that limit stops the whole pipeline.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import multiprocessing as mp
import os
import shutil
import signal
import sys
import time
from dataclasses import dataclass, field
from typing import Any, Optional

import psutil
import zmq

from ..config import ConfigError, PipelineConfig, new_run_dir
from .stage import RunInfo, stage_main

log = logging.getLogger("pointflow.supervisor")


@contextlib.contextmanager
def _main_module_importable():
    """``spawn`` re-runs the parent's ``__main__`` file in each child; when that is not a
    real file (``python -`` or an embedded interpreter) hide it so children start anyway."""
    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    hide = path is not None and not os.path.exists(path)
    if hide:
        del main.__file__
    try:
        yield
    finally:
        if hide:
            main.__file__ = path


class PipelineFailed(RuntimeError):
    """A stage kept failing past its restart limit; the pipeline was stopped."""


@dataclass
class StageProc:
    name: str
    kind: str
    source_index: int = -1
    process: Optional[mp.process.BaseProcess] = None
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
            # the recording (docs/record.md): ingest's copies for it, the recorder's files
            "record_offered", "record_sent", "record_dropped", "record_messages_sent", "record_bytes",
            "record_messages", "record_files",
            "record_transforms_sent", "record_transforms_dropped", "record_transforms")
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
        self._mp = mp.get_context("spawn")
        self._t_start = 0.0
        self._last_ps = 0.0

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
        if self.role == "send":
            self.segments = []
            self.stages["sender"] = StageProc(name="sender", kind="sender")
            for i, s in enumerate(cfg.sources):
                if not s.external:
                    self.stages[s.name] = StageProc(name=s.name, kind="source", source_index=i)
            self._t_start = time.monotonic()
            self.started = True
            # the sender binds the socket the sources push to: start it first and wait for
            # its first heartbeat, so a short replay is not over before anyone listens
            snd = self.stages["sender"]
            self._spawn(snd)
            end = time.monotonic() + cfg.supervisor.startup_timeout_ms / 1000
            while not snd.ready and time.monotonic() < end and snd.process.exitcode is None:
                self.poll(0.05)
            for st in self.stages.values():
                if st is not snd:
                    self._spawn(st)
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
        if cfg.record is not None:  # binds the socket ingest sends its copies to: before ingest
            order.insert(2, ("recorder", "recorder", -1))
        order += [(s.name, "source", i) for i, s in enumerate(cfg.sources) if not s.external]
        for name, kind, idx in order:
            self.stages[name] = StageProc(name=name, kind=kind, source_index=idx)
        self._t_start = time.monotonic()
        self.started = True
        for st in self.stages.values():
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
        p = self._mp.Process(target=stage_main, name=f"pointflow-{st.name}",
                             args=(st.name, st.kind, self.cfg.to_dict(), self.cfg.base_dir, info), daemon=True)
        with _main_module_importable():
            p.start()
        st.process, st.pid = p, p.pid
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
        """Handle control messages and stage exits; call in a loop."""
        if not self.started:
            return
        deadline = time.monotonic() + timeout_s
        while True:
            left = max(0.0, deadline - time.monotonic())
            if self._control.poll(int(left * 1000)):
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
        self._check_stages()
        now = time.monotonic()
        if now - self._last_ps >= 1.0:
            self._last_ps = now
            for st in self.stages.values():
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
        if st is None or msg.get("pid") != st.pid:
            return  # from an earlier incarnation
        now = time.monotonic_ns()
        st.last_seen_ns = now
        kind = msg.get("type")
        if kind == "pulse":
            if st.ready:
                age = msg.get("loop_age_ms", 0)
                st.last_progress_ns = now - int(age * 1e6) if isinstance(age, (int, float)) else st.last_progress_ns
            return
        st.ready = True
        st.last_progress_ns = now
        if kind == "heartbeat":
            st.stats = msg.get("stats", {})
        elif kind == "error":
            st.last_error = msg.get("message", "")
            log.error("%s reported: %s", st.name, st.last_error.strip().splitlines()[-1] if st.last_error.strip() else "")
        elif kind == "done":
            st.finished = True
            if msg.get("stop_pipeline"):
                self.stop_requested = f"{st.name}: {msg.get('reason', 'asked to stop')}"
                log.info("stop requested by %s", self.stop_requested)
            else:
                log.info("%s finished (its input ended)", st.name)

    def _check_stages(self) -> None:
        now = time.monotonic_ns()
        sup = self.cfg.supervisor
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
            limit_ms = sup.hung_after_ms if st.ready else sup.startup_timeout_ms
            silent = (now - st.last_seen_ns) > limit_ms * 1e6
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
                    reason = f"did not start: no heartbeat within {limit_ms:.0f} ms"
                elif silent:
                    reason = f"hung: no heartbeat for {(now - st.last_seen_ns) / 1e6:.0f} ms"
                else:
                    reason = f"stuck: its loop has not come round for {(now - st.last_progress_ns) / 1e6:.0f} ms"
                st.process.kill()
                st.process.join(2)
            else:
                reason = _describe_exit(code)
            self._stage_died(st, reason)

    def _stage_died(self, st: StageProc, reason: str) -> None:
        sup = self.cfg.supervisor
        last = (st.last_error or "").strip().splitlines()
        detail = f"; last error: {last[-1]}" if last else ""
        if st.kind == "ingest":
            self._reconcile_ingest(st)
        st.carried = _merge_counts(st.carried, st.stats)
        st.stats = {}
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
        backoff = sup.restart_backoff_ms * (2 ** (st.restarts - 1))
        log.error("stage %s (pid %d) %s%s; restarting in %.0f ms", st.name, st.pid, reason, detail, backoff)
        st.restart_at_ns = time.monotonic_ns() + int(backoff * 1e6)
        st.last_error = None
        ev["action"] = "restart"
        self.events.append(ev)

    def _reconcile_ingest(self, st: StageProc) -> None:
        """Points a killed ingest wrote after its last heartbeat are in the ring but not in
        its counters; the ring's write count is authoritative, so add them (they were
        received and written)."""
        if self.ring is None:
            return
        try:
            written = int(self.ring.stats().total_written)
        except Exception:  # noqa: BLE001
            return
        reported = int(st.carried.get("points_out", 0)) + int(st.stats.get("points_out", 0))
        if written > reported:
            st.stats = dict(st.stats)
            for k in ("points_in", "points_out"):
                st.stats[k] = int(st.stats.get(k, 0)) + (written - reported)
            log.info("ingest: %d points written after its last heartbeat added to its counts", written - reported)

    def _notify_restart(self, st: StageProc) -> None:
        """A new renderer holds no slab: the cadence must consider both free."""
        # The render stage announces itself to the cadence on the release socket when
        # it starts; nothing else to do here. Kept as a hook for stages that need it.

    # ------------------------------------------------------------------ stop
    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop upstream first: sources, then (once they are gone, so their last chunks are
        in ingest's socket) ingest, which drains before it exits, then cadence and render."""
        if not self.started:
            return
        self.started = False
        sources = [st for st in self.stages.values() if st.kind == "source"]
        waves = [sources, [self.stages[n] for n in ("ingest", "sender") if n in self.stages],
                 [self.stages[n] for n in ("cadence", "render", "recorder") if n in self.stages]]
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
        self.final_stats = self.stats()
        self._release()

    def _drain_control(self, timeout_s: float) -> None:
        if self._control is None:
            return
        if self._control.poll(int(timeout_s * 1000)):
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
        stages = {}
        for st in self.stages.values():
            d = _merge_counts(st.carried, st.stats) if st.carried else dict(st.stats)
            d.setdefault("points_in", 0)
            d.setdefault("points_out", 0)
            d.setdefault("drops", {})
            d.update(pid=st.pid, kind=st.kind, cpu_percent=round(st.cpu_percent, 1), rss_bytes=st.rss_bytes,
                     restarts=st.restarts, alive=bool(st.process is not None and st.process.exitcode is None),
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
            try:
                out["ring"] = self.ring.stats().to_dict()
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
        if ring:
            acc["ring_written"] = ring.get("total_written")
            acc["ring_agrees"] = ring.get("total_written") == acc["ingest_written"]
        sources = [v for v in stages.values() if v.get("kind") == "source"]
        if not any(s.external for s in self.cfg.sources):
            acc["sources_sent"] = sum(v.get("points_out", 0) for v in sources)
            if any(v.get("restarts") for v in sources):
                # a killed source's sends since its last heartbeat died with it
                acc["lost_before_ingest"] = None
            else:
                acc["lost_before_ingest"] = acc["sources_sent"] - acc["ingest_received"]
        if "recorder" in stages:
            acc.update(self._record_accounting(ing, stages["recorder"]))
        link = [v for v in sources if "transport_link_sent" in v]
        if link:
            # zmq sources fed by `pointflow send` (docs/remote.md): what the senders sent
            # since this pipeline joined = what arrived + what the link lost
            acc["link_sent"] = sum(v.get("transport_link_sent", 0) for v in link)
            acc["link_received"] = sum(v.get("transport_link_received", 0) for v in link)
            acc["lost_in_transit"] = sum(v.get("transport_lost_in_transit", 0) for v in link)
            acc["lost_in_transit_by_source"] = {k.split(":", 1)[1]: n for v in link for k, n in v.items()
                                                if k.startswith("transport_lost_in_transit:")}
            acc["link_balanced"] = acc["link_sent"] == acc["link_received"] + acc["lost_in_transit"]
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
