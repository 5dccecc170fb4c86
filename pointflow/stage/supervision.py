"""The supervision contract, the ``supervisor:`` section: how often a stage beats, what
silence and stalls the supervisor judges hung, restarts, standbys (docs/reliability.md),
and the links every stage reports on. Both sides read it: a stage's context beats at
``heartbeat_ms``, the supervisor (pointflow/runtime/) judges; the loader assembles it."""
from __future__ import annotations

from dataclasses import dataclass, field

from ..stage.endpoints import Endpoint
from ..typed import check, non_negative, positive


#: The supervisor's links (PULL bound by the supervisor; every stage PUSHes).
ENDPOINTS = (Endpoint("control", "control", "stages -> supervisor: heartbeats, pulses, errors"),
             Endpoint("trace", "trace", "stages -> supervisor: profiling spans"))


@dataclass
class SupervisorConfig:
    heartbeat_ms: float = field(default=200.0, metadata=check(positive))
    #: A stage process silent for this long (no heartbeat or pulse) is considered hung if
    #: the kernel says it is not running either: stopped (SIGSTOP), or asleep without using
    #: CPU. A silent stage that wants the CPU or uses it is starved, not hung, on a loaded
    #: machine, and is kept up to stall_after_ms (docs/reliability.md).
    hung_after_ms: float = field(default=800.0, metadata=check(positive))
    #: A stage whose main loop has not come round for this long is considered stuck
    #: (generous: one frame of a software rasteriser can take a second or more).
    stall_after_ms: float = field(default=30000.0, metadata=check(positive))
    #: A silent stage whose main thread never slept and used this much CPU since it went
    #: silent spins in a call that holds the GIL (its pulse thread cannot talk): hung.
    #: CPU time, not wall time, so a loaded machine does not trigger it.
    stuck_cpu_ms: float = field(default=3000.0, metadata=check(positive))
    #: Grace period before a new stage's first heartbeat (imports, GPU device creation).
    startup_timeout_ms: float = field(default=30000.0, metadata=check(positive))
    max_restarts: int = field(default=3, metadata=check(non_negative))
    restart_backoff_ms: float = field(default=200.0, metadata=check(non_negative))
    #: Keep a prepared standby process for each render, cadence, ingest and source stage:
    #: interpreter started, modules imported, the renderer's device created and warmed up,
    #: so a restart only hands it its run info.
    standby: bool = True
    #: Start the stages the first time by forking them from one clean interpreter that has
    #: imported numpy, zmq and the stages' modules once (pointflow/runtime/forkserver.py),
    #: instead of one new interpreter each importing them all: a shorter start, most of all
    #: on a busy machine. Restarts and standbys start as new interpreters either way.
    fork_server: bool = True
