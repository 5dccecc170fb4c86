"""A stage starved of CPU is not hung (issue 19: at load 17-32 on 2 cores the supervisor
killed healthy stages after ``hung_after_ms`` 800 ms of silence). The supervisor asks the
kernel (``pointflow/runtime/liveness.py``): a silent stage that wants the CPU or used it is
kept; a frozen one is still replaced.

The test makes the load itself: busy-loop processes, two per core, and every stage
thread at nice 19 so the busy loops take the CPU first. ``hung_after_ms`` is 150 ms, a
little more than the 100-ms pulse period: the stages overrun it again and again."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

from pointflow import Pipeline

from ..helpers import assert_gone, assert_segments_gone, small_config, wait_for


def _renice_all(pid: int, nice: int) -> None:
    """Every thread of ``pid`` (setpriority on a pid changes only its first thread)."""
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            os.setpriority(os.PRIO_PROCESS, int(tid), nice)
        except (ProcessLookupError, PermissionError):
            pass


def test_starved_stages_are_not_hung_and_a_frozen_one_still_is(tmp_path):
    cfg = small_config(supervisor={"max_restarts": 5, "hung_after_ms": 150, "restart_backoff_ms": 50,
                                   "standby": False})
    busy = []
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path)) as pipe:
        assert wait_for(lambda: pipe.stats()["frames"] >= 2, 60)
        stages = pipe.stats()["stages"]
        pids = {n: v["pid"] for n, v in stages.items()}
        try:
            for _ in range(2 * (os.cpu_count() or 1)):
                busy.append(subprocess.Popen([sys.executable, "-c", "while True: pass"]))
            for pid in pids.values():
                _renice_all(pid, 19)
            time.sleep(10.0)
            st = pipe.stats()
            starved = {n: v.get("starved_silences", 0) for n, v in st["stages"].items()}
            hung = [e for e in st["events"] if "hung" in e["reason"]]
            assert not hung, f"starved stages killed as hung: {hung} (starved silences {starved})"
            # the load did make them silent past hung_after_ms (else this test proves nothing)
            assert sum(starved.values()) >= 1, starved
            assert {n: v["pid"] for n, v in st["stages"].items()} == pids
            # a frozen stage under the same load is still found and replaced
            os.kill(pids["ingest"], signal.SIGSTOP)
            try:
                assert wait_for(lambda: pipe.stats()["stages"]["ingest"]["pid"] != pids["ingest"], 60)
            finally:
                try:
                    os.kill(pids["ingest"], signal.SIGCONT)
                except ProcessLookupError:
                    pass
        finally:
            for p in busy:
                p.kill()
                p.wait()
        events = pipe.stats()["events"]
        assert [(e["stage"], e["pid"]) for e in events] == [("ingest", pids["ingest"])], events
        assert "hung" in events[0]["reason"]
        pipe.wait(60, until=lambda: pipe.stats()["stages"]["ingest"]["ready"])
        final_pids = [v["pid"] for v in pipe.stats()["stages"].values()]
    st = pipe.stats()
    assert_segments_gone(st)
    assert_gone(list(pids.values()) + final_pids)
