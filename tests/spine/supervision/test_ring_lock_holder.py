"""Supervision and ``stats()`` never wait for the ring's lock (issue 31).

A stage can stop while it holds the ring's lock: SIGSTOP or a debugger in the middle of a
push, or, on a loaded machine, an ingest descheduled inside one. ``stats()`` used to read
the ring's counters under that lock while it held the supervisor's own lock, so a caller
that polled ``stats()`` (the CLI's progress line does, twice a second) waited for the
frozen stage, and the supervision thread waited for the caller: the frozen ingest was
never replaced and the run hung until someone sent SIGCONT.

What holds now, on a quiet or a loaded machine: ``stats()`` answers while a frozen stage
holds the ring's lock, the frozen ingest is replaced as hung (its threads are stopped:
``T`` in /proc), and the accounting is exact at the end (the ring's counters, read without
the lock once no process writes, are the truth). Nothing here is timed; the waits are long
enough for a loaded machine."""
from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np

from pointflow import Pipeline

from ..helpers import assert_gone, assert_segments_gone, small_config


def _flock_holders(path: str) -> set[int]:
    """Pids holding an flock on ``path`` (from /proc/locks)."""
    ino = os.stat(path).st_ino
    pids = set()
    with open("/proc/locks") as f:
        for line in f:
            parts = line.split()
            if "->" in parts:  # a waiter, not a holder
                continue
            if len(parts) >= 6 and parts[1] == "FLOCK":
                dev_ino = parts[5].split(":")
                if len(dev_ino) == 3 and int(dev_ino[2]) == ino:
                    pids.add(int(parts[4]))
    return pids


def _freeze_inside_a_push(pid: int, ring_path: str, tries: int = 2000) -> bool:
    """SIGSTOP ``pid`` until it is stopped while it holds the ring's lock."""
    for _ in range(tries):
        os.kill(pid, signal.SIGSTOP)
        time.sleep(0.005)  # let the stop land
        if pid in _flock_holders(ring_path):
            return True
        os.kill(pid, signal.SIGCONT)
        time.sleep(0.001 * (1 + _ % 7))
    return False


def test_a_stage_frozen_inside_a_push_stops_neither_stats_nor_supervision(tmp_path):
    rng = np.random.default_rng(5)
    data = np.column_stack([rng.uniform(-20, 20, (600_000, 3)), rng.uniform(0, 1, 600_000)]).astype(np.float32)
    np.save(tmp_path / "cloud.npy", data)
    # big chunks into a big ring: ingest spends much of its time inside push (under the lock)
    cfg = small_config(source={"transport": "file", "options": {
                           "path": str(tmp_path / "cloud.npy"), "chunk_points": 200_000, "realtime": False,
                           "loop": True}},
                       ring={"max_points": 1_000_000},
                       supervisor={"max_restarts": 3, "restart_backoff_ms": 50, "standby": False})
    pipe = Pipeline.from_dict(cfg, out_dir=str(tmp_path / "out"))
    with pipe:
        pipe.wait(120, until=lambda: pipe.stats()["stages"]["ingest"]["ready"]
                  and pipe.stats()["ring"]["total_written"] > 0)
        st = pipe.stats()
        ring_path = os.path.join("/dev/shm", st["shm_segments"][0])
        pid = st["stages"]["ingest"]["pid"]
        assert _freeze_inside_a_push(pid, ring_path), "never caught ingest inside a push"
        try:
            # a caller polls stats() while the frozen ingest holds the ring's lock
            answers: list[dict] = []
            def poll() -> None:
                for _ in range(20):
                    answers.append(pipe.stats())
                    time.sleep(0.05)
            t = threading.Thread(target=poll, daemon=True)
            t.start()
            t.join(60)
            assert not t.is_alive(), "stats() waited for the ring's lock held by a frozen ingest"
            assert len(answers) == 20
            # ...and the supervisor replaces the frozen ingest meanwhile
            pipe.wait(120, until=lambda: pipe.stats()["stages"]["ingest"]["pid"] != pid)
            assert pipe.stats()["stages"]["ingest"]["pid"] != pid, "the frozen ingest was not replaced"
        finally:
            try:
                os.kill(pid, signal.SIGCONT)
            except ProcessLookupError:
                pass
        ev = [e for e in pipe.stats()["events"] if e["pid"] == pid]
        assert ev and ev[0]["stage"] == "ingest" and ev[0]["reason"].startswith("hung"), pipe.stats()["events"]
        # the new ingest writes again
        w = pipe.stats()["ring"]["total_written"]
        pipe.wait(120, until=lambda: pipe.stats()["ring"]["total_written"] > w)
        pids = {s["pid"] for s in pipe.stats()["stages"].values()} | {pid}
    final = pipe.stats()
    acc = final["accounting"]
    assert acc["ring_agrees"] and acc["ingest_balanced"], acc
    assert final["stages"]["ingest"]["restarts"] >= 1
    assert_gone(pids)
    assert_segments_gone(final)
