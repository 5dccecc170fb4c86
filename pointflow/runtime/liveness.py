"""Is a silent stage hung, or only starved of CPU? Asked of the kernel, not the wall clock.

A stage that sends nothing for ``supervisor.hung_after_ms`` is not necessarily hung: on a
loaded machine (load 17-32 on 2 cores in issue 19's soak) healthy stages went silent for
0.8-1.9 s and were killed, which only made the load worse. The kernel knows the
difference: a starved process has a thread waiting to run (state ``R``) or waiting for
the disk (``D``), or it used CPU time since it was last checked; a frozen one is stopped
(``T``); a hung one sleeps (``S``) and uses no CPU time at all (a deadlock, a call that
never returns while holding the GIL, so not even its pulse thread can talk).

One case uses the CPU and is still hung: a main thread spinning in a C call that holds the
GIL (a runaway regular expression, a C extension's busy loop). Its pulse thread cannot talk,
and it looks starved. What gives it away is its main thread: never asleep during the
silence and on the CPU for ``supervisor.stuck_cpu_ms`` of it. A healthy stage's main thread
waits (for the GPU, a socket, the ring) and lets the pulse through long before that.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Optional

_CLK_TCK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


@dataclass(frozen=True)
class Activity:
    """A snapshot of a process, from ``/proc/<pid>``."""

    stopped: bool    # SIGSTOP / job control / a tracer: every thread is in T or t
    runnable: bool   # some thread is running, waiting for a CPU (R) or for the disk (D)
    cpu_s: float     # user + system CPU time of all its threads so far
    main_awake: bool = False  # its main thread is running or waiting for a CPU (R), not asleep
    main_cpu_s: float = 0.0   # CPU time of its main thread so far

    def running_since(self, before: "Activity", elapsed_s: float) -> bool:
        """It wants the CPU now, or used at least 2% of one (1 ms at least) since ``before``.
        A thread that waits for the GIL wakes every 5 ms (CPython's switch interval) and
        uses ~0.2% of a CPU doing so: a process hung in a C call that holds the GIL must
        not look busy."""
        return self.runnable or (self.cpu_s - before.cpu_s) >= max(0.001, 0.02 * elapsed_s)


def _state_and_times(stat: str) -> tuple[str, float]:
    # comm (field 2) may contain spaces and parentheses: split after the last ')'
    rest = stat[stat.rindex(")") + 2:].split()
    return rest[0], (int(rest[11]) + int(rest[12])) / _CLK_TCK  # state, utime + stime


def activity(pid: int) -> Optional[Activity]:
    """What ``pid`` is doing now; None when it is gone (or /proc cannot tell: not Linux)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            state, cpu = _state_and_times(f.read())
        states, run_ns = [], 0
        main_state, main_ns = state, 0
        for tid in os.listdir(f"/proc/{pid}/task"):
            try:
                with open(f"/proc/{pid}/task/{tid}/stat") as f:
                    tstate = _state_and_times(f.read())[0]
                states.append(tstate)
            except (FileNotFoundError, ProcessLookupError):
                continue  # the thread ended meanwhile
            try:  # nanoseconds on a CPU (the stat ticks are 10 ms: too coarse for a pulse)
                with open(f"/proc/{pid}/task/{tid}/schedstat") as f:
                    ns = int(f.read().split()[0])
                run_ns += ns
            except (FileNotFoundError, ProcessLookupError):
                ns = 0  # a kernel without schedstat: the ticks it is
            if tid == str(pid):
                main_state, main_ns = tstate, ns
    except (FileNotFoundError, ProcessLookupError, PermissionError, ValueError, IndexError):
        return None
    if state in ("Z", "X"):
        return None
    states = states or [state]
    return Activity(stopped=all(s in ("T", "t") for s in states),
                    runnable=any(s in ("R", "D") for s in states), cpu_s=max(cpu, run_ns / 1e9),
                    main_awake=main_state == "R", main_cpu_s=main_ns / 1e9)
