"""Running a pipeline: the processes, who starts them, and what they share.

* :mod:`.kinds`: what a stage kind is (:class:`StageKind`, :func:`register_stage_kind`,
  :func:`stage_kind`, :func:`stage_kinds`), one record per kind, declared next to its code;
* :mod:`.stage`: what every stage process shares (:class:`StageContext`: heartbeats,
  counters, spans, stop) and :func:`~.stage.stage_main`, its entry; :mod:`.launch` starts
  one as a fresh interpreter (or a prepared standby);
* :mod:`.supervisor`: the lifecycle (start in order, watch, restart, stop in waves);
  :mod:`.accounting` (where every point went), :mod:`.liveness` (hung or starved),
  :mod:`.stagestate` (what it knows of one stage), :mod:`.rundir` (the run directory of
  ipc sockets), :mod:`.console` (log lines on a terminal);
* :mod:`.pipeline`: :class:`Pipeline`, the Python API over a supervisor.
"""
from .._lazy import lazy_exports

__getattr__ = lazy_exports(__name__, {
    "Pipeline": ".pipeline", "PipelineFailed": ".supervisor", "StageContext": ".stage",
    "StageKind": ".kinds", "register_stage_kind": ".kinds", "stage_kind": ".kinds", "stage_kinds": ".kinds",
})

__all__ = ["Pipeline", "PipelineFailed", "StageContext", "StageKind", "register_stage_kind", "stage_kind",
           "stage_kinds"]
