"""Running a pipeline: the processes, who starts them, and what they watch.

What every stage imports (its context, its kind's record, counters, the console) is the
stage kit, :mod:`pointflow.stage`, below the stages; this package sits above them:

* :mod:`.stage`: a stage process's entry (:func:`~.stage.stage_main`); :mod:`.launch` starts
  one as a fresh interpreter (or a prepared standby), :mod:`.forkserver` forks the first ones;
* :mod:`.supervisor`: the lifecycle (start in order, watch, restart, stop in waves);
  :mod:`.accounting` (counters over restarts, the run's identities), :mod:`.liveness` (hung
  or starved), :mod:`.stagestate` (what it knows of one stage), :mod:`.rundir` (the run
  directory of ipc sockets);
* :mod:`.pipeline`: :class:`Pipeline`, the Python API over a supervisor;
* :mod:`.testing`: one stage in a process without a supervisor, for tests and bench/.
"""
from .._lazy import lazy_exports

__getattr__ = lazy_exports(__name__, {"Pipeline": ".pipeline", "PipelineFailed": ".supervisor"})

__all__ = ["Pipeline", "PipelineFailed"]
