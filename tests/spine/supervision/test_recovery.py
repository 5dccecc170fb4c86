"""Fault recovery: SIGKILL each stage in turn; the run recovers, frames resume, the
ingest accounting stays exact, the ring keeps its points, nothing leaks."""
from __future__ import annotations

import os
import signal

import pytest

from pointflow import Pipeline
from pointflow.runtime.supervisor import PipelineFailed

from ..helpers import assert_gone, assert_segments_gone, small_config


def _ingest_balanced(st: dict) -> bool:
    ing = st["stages"]["ingest"]
    return ing["points_in"] == ing["points_out"] + sum(ing["drops"].values())


def test_kill_each_stage_in_turn_recovers(tmp_path):
    """Each SIGKILLed stage is restarted once and frames resume; nothing else restarts.

    On a loaded machine (load 17-32 on 2 cores) the product guarantees the same outcome,
    not its speed: a restarted stage may take tens of seconds to report in (a fresh
    interpreter and its imports) and a starved stage is not judged hung (liveness from
    the kernel's run state, runtime/liveness.py), so the only restarts are the kills. The
    waits are long enough for that (120 s each); nothing here is timed."""
    cfg = small_config(supervisor={"max_restarts": 2, "restart_backoff_ms": 50, "hung_after_ms": 1000})
    pipe = Pipeline.from_dict(cfg, out_dir=str(tmp_path))
    all_pids = set()
    with pipe:
        pipe.wait(120, until=lambda: pipe.stats()["frames"] >= 3)
        for stage in ("render", "cadence", "ingest", "source"):
            st = pipe.stats()
            old_pid = st["stages"][stage]["pid"]
            frames_before = st["frames"]
            ring_before = st["ring"]["total_points"]
            all_pids.update(s["pid"] for s in st["stages"].values())
            os.kill(old_pid, signal.SIGKILL)
            # restarted with a new pid, and frames resume
            pipe.wait(120, until=lambda: pipe.stats()["stages"][stage]["pid"] != old_pid
                      and pipe.stats()["stages"][stage]["alive"])
            pipe.wait(120, until=lambda: pipe.stats()["frames"] >= frames_before + 3)
            st = pipe.stats()
            assert st["stages"][stage]["pid"] != old_pid, f"{stage} was not restarted"
            assert st["stages"][stage]["restarts"] == 1
            assert st["frames"] >= frames_before + 3, f"frames did not resume after killing {stage}"
            assert st["ring"]["total_points"] >= ring_before, "the ring lost points (FIFO never shrinks)"
            ev = st["events"][-1]
            assert ev["stage"] == stage and ev["action"] == "restart" and "SIGKILL" in ev["reason"]
        all_pids.update(s["pid"] for s in pipe.stats()["stages"].values())
    final = pipe.stats()
    assert _ingest_balanced(final), final["stages"]["ingest"]
    assert final["ring"]["total_written"] == final["stages"]["ingest"]["points_out"], "ring and ingest disagree"
    acc = final["accounting"]
    assert acc["ingest_balanced"] and acc["ring_agrees"]
    # the source was killed too, so what it sent after its last heartbeat is unknowable
    assert acc["lost_before_ingest"] is None
    assert final["frames"] >= 15, "frame count must carry over render restarts"
    pngs = sorted(tmp_path.glob("frame_*.png"))
    assert len(pngs) == final["stages"]["render"]["pngs"], "a restarted renderer overwrote earlier frames"
    assert all(s["restarts"] == 1 for s in final["stages"].values())
    assert_gone(all_pids)
    assert_segments_gone(final)


def test_restart_limit_stops_the_pipeline(tmp_path):
    """The second death of a stage allowed one restart stops the run with PipelineFailed.
    Load changes only how long the restart takes (waits of 120 s), not the outcome."""
    cfg = small_config(supervisor={"max_restarts": 1, "restart_backoff_ms": 50})
    pipe = Pipeline.from_dict(cfg, out_dir=str(tmp_path))
    pipe.start()
    try:
        pipe.wait(120, until=lambda: pipe.stats()["frames"] >= 1)
        os.kill(pipe.stats()["stages"]["render"]["pid"], signal.SIGKILL)
        old = pipe.stats()["stages"]["render"]["pid"]
        pipe.wait(120, until=lambda: pipe.stats()["stages"]["render"]["pid"] != old)
        pipe.wait(120, until=lambda: pipe.stats()["stages"]["render"]["alive"])
        os.kill(pipe.stats()["stages"]["render"]["pid"], signal.SIGKILL)
        with pytest.raises(PipelineFailed, match="render.*restart limit 1 reached"):
            pipe.wait(120)
    finally:
        stats = pipe.stop()
    assert [e["action"] for e in stats["events"]] == ["restart", "stop"]
    assert_segments_gone(stats)


def test_a_frozen_stage_is_detected_and_restarted(tmp_path):
    """SIGSTOP freezes a stage: no heartbeat, no pulse. The supervisor kills it after
    ``hung_after_ms`` and restarts it; the run goes on.

    On a loaded machine the guarantee is the same: a frozen stage (every thread stopped,
    ``T`` in /proc) is hung at once whatever the load, and the healthy stages around it,
    starved or not, are not killed (runtime/liveness.py); so the only event is the frozen
    ingest's. What load changes is how long its successor takes to start and ingest again
    (waits of 120 s, nothing timed)."""
    cfg = small_config(supervisor={"max_restarts": 1, "restart_backoff_ms": 50, "hung_after_ms": 800})
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path)) as pipe:
        pipe.wait(120, until=lambda: pipe.stats()["frames"] >= 2)
        old = pipe.stats()["stages"]["ingest"]["pid"]
        os.kill(old, signal.SIGSTOP)
        pipe.wait(120, until=lambda: pipe.stats()["stages"]["ingest"]["pid"] != old
                  and pipe.stats()["stages"]["ingest"]["alive"])
        n0 = pipe.stats()["stages"]["ingest"]["points_in"]
        pipe.wait(120, until=lambda: pipe.stats()["stages"]["ingest"]["points_in"] > n0)
        st = pipe.stats()
    assert [(e["stage"], e["pid"]) for e in st["events"]] == [("ingest", old)], st["events"]
    ev = st["events"][0]
    assert ev["action"] == "restart" and ev["reason"].startswith("hung")
    assert st["stages"]["ingest"]["points_in"] > n0, "ingest did not resume"
    assert_gone([old])
    assert_segments_gone(pipe.stats())


def test_send_raises_once_the_pipeline_failed(tmp_path):
    """A thread sending while ingest dies past its restart limit gets PipelineFailed from
    send, and so does every later send: it waited for ingest forever (a black-box run)."""
    import threading

    import numpy as np

    cfg = small_config(source={"transport": "api", "name": "cam"}, supervisor={"max_restarts": 0})
    pipe = Pipeline.from_dict(cfg, out_dir=str(tmp_path))
    pipe.start()
    got: list = []
    xyz = np.random.default_rng(0).normal(size=(200_000, 3)).astype(np.float32)

    def sender() -> None:
        try:
            while True:
                pipe.send(xyz, source="cam")
        except BaseException as exc:  # noqa: BLE001 - what send raised is the test's answer
            got.append(exc)

    t = threading.Thread(target=sender, daemon=True)
    try:
        t.start()
        pipe.wait(120, until=lambda: pipe.stats()["stages"]["ingest"]["points_in"] > 0)
        os.kill(pipe.stats()["stages"]["ingest"]["pid"], signal.SIGKILL)
        t.join(180)
        assert not t.is_alive(), "send still waiting for an ingest that is gone"
        assert len(got) == 1 and isinstance(got[0], PipelineFailed) and "ingest" in str(got[0]), got
        with pytest.raises(PipelineFailed):
            pipe.send(xyz[:10], source="cam")
    finally:
        pipe.stop()
