"""Start a stage as its own interpreter: ``python -m pointflow.runtime.launch``.

``multiprocessing``'s ``spawn`` re-imports the caller's ``__main__`` in every child, so a
script without an ``if __name__ == "__main__":`` guard (the README's example saved as a
file), ``python -c``, a notebook or a frozen main either fails or re-runs the caller's
code in each stage. Here a stage is a plain ``subprocess`` running this module; what
:func:`pointflow.runtime.stage.stage_main` needs (stage name and kind, the config as a
dict, base dir, :class:`~pointflow.stage.context.RunInfo`) arrives pickled on its stdin,
so nothing of the caller's ``__main__`` is ever imported. The stage still arms
``PR_SET_PDEATHSIG`` first thing, so it cannot outlive the supervisor.
"""
from __future__ import annotations

import os
import pickle
import subprocess
import sys
import time
from typing import Optional

#: The directory that holds the ``pointflow`` package (this file is
#: ``pointflow/runtime/launch.py``), put first on the stage's ``PYTHONPATH`` so a checkout
#: used without installing is found by the child too.
_PKG_PARENT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


#: Thread-pool sizes of the BLAS / OpenMP libraries numpy may use, set to 1 in stages.
_ONE_THREAD = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


class StageProcess:
    """A stage's OS process, with the small part of ``multiprocessing.Process``'s interface
    the supervisor uses (``pid``, ``exitcode``, ``terminate``, ``kill``, ``join``).

    A *standby* (``spawn_stage(..., standby=True)``) has imported its stage and prepared
    what does not depend on the incarnation (the renderer's device and pipelines) and waits
    for :meth:`activate` to hand it its :class:`~pointflow.stage.context.RunInfo`."""

    def __init__(self, popen: subprocess.Popen, standby: bool = False):
        self._p = popen
        self.pid = popen.pid
        self.standby = standby

    def activate(self, info) -> bool:
        """Start a standby as the stage's new incarnation; False if it is gone."""
        if not self.standby or self._p.poll() is not None:
            return False
        try:
            self._p.stdin.write(pickle.dumps(info, protocol=pickle.HIGHEST_PROTOCOL))
            self._p.stdin.close()
        except (OSError, ValueError):
            return False
        self.standby = False
        return True

    @property
    def exitcode(self) -> Optional[int]:
        return self._p.poll()

    def is_alive(self) -> bool:
        return self._p.poll() is None

    def terminate(self) -> None:
        if self._p.poll() is None:
            self._p.terminate()

    def kill(self) -> None:
        if self._p.poll() is None:
            self._p.kill()

    def join(self, timeout: Optional[float] = None) -> None:
        try:
            self._p.wait(timeout)
        except subprocess.TimeoutExpired:
            pass


def spawn_stage(name: str, kind, cfg_dict: dict, base_dir: str, info, standby: bool = False) -> StageProcess:
    """Start ``stage_main(name, kind, cfg_dict, base_dir, info)`` in a new interpreter; with
    ``standby`` it prepares and then waits for :meth:`StageProcess.activate`. ``kind`` is the
    :class:`~pointflow.stage.kinds.StageKind` record (or its name)."""
    payload = pickle.dumps((name, kind, cfg_dict, base_dir, info, standby), protocol=pickle.HIGHEST_PROTOCOL)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (_PKG_PARENT, env.get("PYTHONPATH", "")) if p)
    # A stage is one process doing one thing; BLAS thread pools in every stage fight each
    # other and lavapipe's threads. The frames step's (N, 3) @ (3, 3) ran 2.4x slower with
    # OpenBLAS's default threads than with one, on an idle 2-core machine (bench_frames.py).
    # A value the user set is kept.
    for var in _ONE_THREAD:
        env.setdefault(var, "1")
    p = subprocess.Popen([sys.executable, "-m", "pointflow.runtime.launch", name], stdin=subprocess.PIPE,
                         env=env, close_fds=True)
    try:
        p.stdin.write(payload)
        if standby:
            p.stdin.flush()
        else:
            p.stdin.close()
    except OSError:  # it died before reading: its exit code says why
        pass
    return StageProcess(p, standby=standby)


def _main() -> None:
    t_main = time.monotonic_ns()  # the interpreter is up and ``pointflow`` imported (startup marks)
    # before anything slow: a supervisor killed from here on still takes the stage with it
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, 15)  # PR_SET_PDEATHSIG, SIGTERM
    except OSError:
        pass
    from .rundir import ensure_runtime_dir

    ensure_runtime_dir()
    name, kind, cfg_dict, base_dir, info, standby = pickle.load(sys.stdin.buffer)
    if os.getppid() != info.supervisor_pid:  # it died before PDEATHSIG was armed
        sys.exit(1)
    from .stage import prepare_stage, stage_main

    prepared = None
    if standby:
        prepared = prepare_stage(name, kind, cfg_dict, base_dir, info)
        try:  # wait until the supervisor needs this incarnation (or discards it: EOF)
            info = pickle.load(sys.stdin.buffer)
        except (EOFError, pickle.UnpicklingError, OSError):
            sys.exit(0)
        if os.getppid() != info.supervisor_pid:
            sys.exit(1)
    if not standby:  # a standby's interpreter came up before this incarnation was asked for
        info.extra.setdefault("t_main_ns", t_main)
    stage_main(name, kind, cfg_dict, base_dir, info, prepared=prepared)


if __name__ == "__main__":
    _main()
