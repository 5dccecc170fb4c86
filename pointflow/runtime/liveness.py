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
import time
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


# ---------------------------------------------------------------------- hang judgement
#: When several stages are silent at once, one counts as hung only after this many
#: times ``supervisor.hung_after_ms`` (at most ``stall_after_ms``).
STALLED_HUNG_FACTOR = 5
#: A stage that has not reported in within ``supervisor.startup_timeout_ms`` but is still
#: starting (using the CPU, or waiting for one) is kept up to this many times the timeout
#: (and at least ``supervisor.stall_after_ms``).
STARTUP_LOAD_FACTOR = 4


def hang_reason(st, now: int, sup, stages) -> Optional[str]:
    """Why the live stage ``st`` (the supervisor's record of it) counts as hung now, or
    None while it does not: it did not report in within ``startup_timeout_ms`` and is not
    still starting, it has been silent past ``hung_after_ms`` and is not merely starved,
    or its loop has not come round for ``stall_after_ms``. ``sup`` is the ``supervisor:``
    config, ``stages`` all the supervisor's stage records. May update ``st``'s marks."""
    limit_ms = sup.hung_after_ms if st.ready else sup.startup_timeout_ms
    silent = (now - st.last_seen_ns) > limit_ms * 1e6
    if silent and st.ready:
        silent = silence_is_hang(st, now, limit_ms, sup, stages)
    elif silent:
        silent = start_is_stuck(st, now, limit_ms, sup)
    stalled = st.ready and (now - st.last_progress_ns) > sup.stall_after_ms * 1e6
    if not st.ready and silent:
        return f"did not start: no heartbeat within {(now - st.started_ns) / 1e6:.0f} ms"
    if silent:
        return f"hung: no heartbeat for {(now - st.last_seen_ns) / 1e6:.0f} ms{st.hang_note}"
    if stalled:
        return f"stuck: its loop has not come round for {(now - st.last_progress_ns) / 1e6:.0f} ms"
    return None


def silence_is_hang(st, now: int, limit_ms: float, sup, stages) -> bool:
    """A stage silent for ``limit_ms``: hung, or starved of CPU on a loaded machine?
    The kernel says (:func:`activity`). Starved (a thread waiting to run or for the
    disk, or CPU time used since the silence began): not hung, however long, up to
    ``stall_after_ms``. Frozen (SIGSTOP): hung now. Asleep without using any CPU for
    half of ``limit_ms`` (at least 250 ms) of watching: hung (a deadlock). The last two
    only when the other stages talk, or after a longer silence when they do not (the
    machine, or this process, stalled)."""
    quiet = now - st.last_seen_ns
    if quiet > sup.stall_after_ms * 1e6:
        return True
    act = activity(st.pid)
    if act is None:
        return False  # it ended: its exit code tells why, next round
    st.hang_note = ""
    if _spins_holding_the_gil(st, act, sup):
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
    if _silent_alone(st, stages, limit_ms):
        return True
    # others went quiet too: the machine (or this process) stalled; only a longer
    # silence counts then
    return quiet > max(limit_ms, min(sup.stall_after_ms, STALLED_HUNG_FACTOR * limit_ms)) * 1e6


def start_is_stuck(st, now: int, limit_ms: float, sup) -> bool:
    """Not reported in within ``startup_timeout_ms``: stuck, or still starting on a
    loaded machine? A fresh interpreter importing numpy, ZeroMQ and wgpu took 13-32 s to
    start a pipeline at load 14-18 on 2 cores; killing it there only starts the same
    work again. Still starting (it used at least 2% of a CPU since the last look, or a
    thread waits for one): kept, up to ``STARTUP_LOAD_FACTOR`` x the timeout (at least
    ``stall_after_ms``). Frozen (SIGSTOP), or asleep without using the CPU for a second
    of watching: did not start."""
    if now - st.started_ns > max(STARTUP_LOAD_FACTOR * limit_ms, sup.stall_after_ms) * 1e6:
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


def _spins_holding_the_gil(st, act: Activity, sup) -> bool:
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
    if awake and used_s * 1000.0 >= sup.stuck_cpu_ms:
        st.hang_note = (f"; its main thread ran {used_s:.1f} s of CPU and never slept: "
                        "stuck in a call that holds the GIL")
        return True
    return False


def _silent_alone(st, stages, limit_ms: float) -> bool:
    """True when every other live stage was heard from within the last half
    ``limit_ms``: the rest of the pipeline is running while ``st`` is not (a frozen or
    hung process). When several stages went silent together, the machine (or this
    process) stalled: at load 15-20 on 2 cores three healthy stages went quiet for
    0.9-1.9 s at once while the fourth still talked, and killing them only made it
    worse."""
    now = time.monotonic_ns()
    others = [o.last_seen_ns for o in stages
              if o is not st and o.ready and not o.dead and o.process is not None and o.process.exitcode is None]
    return all(now - t <= limit_ms * 1e6 / 2 for t in others)
