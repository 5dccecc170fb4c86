"""The first start of the stages forks them from a fork server (issue 36, item 3): they are
children of one clean interpreter that imported their modules once, not of the caller; a
forked stage that dies is judged by its real exit and restarted as a new interpreter; with
``supervisor.fork_server: false`` every stage is a new interpreter, the caller's child."""
from __future__ import annotations

import os
import signal

import psutil

from pointflow import Pipeline

from ..helpers import assert_gone, assert_segments_gone, small_config, wait_for


def _stage_pids(p) -> dict[str, int]:
    return {n: v["pid"] for n, v in p.stats()["stages"].items()}


def test_stages_are_forked_from_the_server_and_a_killed_one_comes_back(tmp_path):
    cfg = small_config(supervisor={"max_restarts": 2, "standby": False})
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path / "out")) as p:
        pids = _stage_pids(p)
        parents = {psutil.Process(pid).ppid() for pid in pids.values()}
        assert len(parents) == 1, parents  # one fork server for every stage
        server = psutil.Process(parents.pop())
        assert server.ppid() == os.getpid() and "pointflow.runtime.forkserver" in " ".join(server.cmdline())
        for name, st in p.stats()["stages"].items():  # each says where its start went
            marks = st["startup_ms"]
            assert set(marks) >= {"module", "context", "setup", "ready"}, (name, marks)
            assert marks["ready"] >= marks["setup"] >= 0, (name, marks)
        os.kill(pids["cadence"], signal.SIGKILL)
        assert wait_for(lambda: p.stats()["stages"]["cadence"]["ready"] and
                        p.stats()["stages"]["cadence"]["pid"] != pids["cadence"], timeout=120)
        new = p.stats()["stages"]["cadence"]["pid"]
        assert psutil.Process(new).ppid() == os.getpid()  # a restart is a new interpreter
        ev = p.stats()["events"]
        assert [(e["stage"], e["reason"], e["action"]) for e in ev] == [("cadence", "killed by signal SIGKILL", "restart")]
        assert server.is_running()  # it still serves the first incarnations it forked
    stats = p.stats()
    assert_gone([*pids.values(), new, server.pid])
    assert_segments_gone(stats)


def test_without_the_fork_server_every_stage_is_the_callers_child(tmp_path):
    cfg = small_config(supervisor={"fork_server": False, "standby": False})
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path / "out")) as p:
        pids = _stage_pids(p)
        assert {psutil.Process(pid).ppid() for pid in pids.values()} == {os.getpid()}
        assert all(v["startup_ms"]["interpreter"] > 0 for v in p.stats()["stages"].values())
    assert_gone(pids.values())
