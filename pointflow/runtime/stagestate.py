"""What the supervisor knows of one stage: its process, its incarnations' counters, the
marks its liveness is judged by (:mod:`.liveness`), and the stats entry it shows."""
from __future__ import annotations

import signal
from dataclasses import dataclass, field
from typing import Any, Optional

import psutil

from .accounting import merge_counts
from .launch import StageProcess


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
    ready_ns: int = 0          # when it did (monotonic, as started_ns)
    #: The stage's startup marks (monotonic ns): ``main`` (interpreter up, pointflow imported),
    #: ``runtime`` (the stage runtime imported), ``module`` (config loaded, the stage's module
    #: imported), ``context`` (its sockets to the supervisor open): :meth:`startup_ms`.
    marks: dict[str, int] = field(default_factory=dict)
    restarts: int = 0
    stats: dict[str, Any] = field(default_factory=dict)
    last_error: Optional[str] = None
    #: The last error's fields (:func:`pointflow.errors.to_fields`), as the stage sent them.
    last_error_fields: Optional[dict] = None
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

    def watch(self, pid: int) -> None:
        """A new incarnation: CPU and memory are sampled from here on."""
        try:
            self.psproc = psutil.Process(pid)
            self.psproc.cpu_percent(None)
        except psutil.Error:
            self.psproc = None

    def sample(self) -> None:
        if self.psproc is not None:
            try:
                self.cpu_percent = self.psproc.cpu_percent(None)
                self.rss_bytes = self.psproc.memory_info().rss
            except psutil.Error:
                pass

    def startup_ms(self) -> dict[str, float]:
        """Where this incarnation's start went, ms per step from its spawn to its first
        heartbeat: ``interpreter`` (a new Python and ``import pointflow``: numpy, the config
        schema), ``runtime`` (the stage runtime, zmq), ``module`` (the config loaded, the
        stage's own module), ``context`` (its sockets to the supervisor), ``setup`` (what its
        loop does before it first reports: binding, a render tier's device and warm-up), and
        ``ready`` (spawn to first heartbeat). Steps not reached yet are missing."""
        if self.local is not None or not self.started_ns:
            return {}
        order = [("interpreter", "main"), ("runtime", "runtime"), ("module", "module"), ("context", "context")]
        out: dict[str, float] = {}
        prev = self.started_ns
        for label, key in order:
            t = self.marks.get(key)
            if t is None:
                break
            out[label] = round((t - prev) / 1e6, 1)
            prev = t
        if self.ready_ns:
            if "context" in out:
                out["setup"] = round((self.ready_ns - prev) / 1e6, 1)
            out["ready"] = round((self.ready_ns - self.started_ns) / 1e6, 1)
        return out

    def report(self, counters: frozenset[str]) -> dict[str, Any]:
        """The stage's entry in ``stats()["stages"]``: its counts over every incarnation
        (``counters`` are summed, the rest is the live one's), how it runs, and whether."""
        if self.local is not None:
            self.stats = self.local.stats()
        d = merge_counts(self.carried, self.stats, counters) if self.carried else dict(self.stats)
        d.setdefault("points_in", 0)
        d.setdefault("points_out", 0)
        d.setdefault("drops", {})
        d.update(pid=self.pid, kind=self.kind, cpu_percent=round(self.cpu_percent, 1), rss_bytes=self.rss_bytes,
                 restarts=self.restarts, alive=bool(self.process is not None and self.process.exitcode is None)
                 or bool(self.local is not None and not self.local.closed),
                 ready=self.ready,  # this incarnation has reported in
                 standby_pid=self.standby.pid if self.standby is not None else None,
                 starved_silences=self.starved,  # silent past hung_after_ms, but running: kept
                 finished=self.finished, startup_ms=self.startup_ms())
        if self.last_error:
            d["last_error"] = self.last_error[-2000:]
        return d


def describe_exit(code: Optional[int]) -> str:
    if code is None:
        return "still running"
    if code < 0:
        try:
            return f"killed by signal {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exited with code {code}"
