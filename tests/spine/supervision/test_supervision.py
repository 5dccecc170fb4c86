"""Supervision that needs no caller (issue 19): stages start without re-importing the
caller's ``__main__`` (the README's example as a script, ``python -c``, stdin), restarts
and stats run in the background while the caller only sleeps, and the accounting stays
exact when ingest is SIGKILLed, even right before the stop."""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from pointflow import Pipeline

from ..helpers import assert_gone, assert_segments_gone, small_config

ROOT = Path(__file__).resolve().parents[3]


def _readme_python_example() -> str:
    """The README's "From Python" block, verbatim."""
    text = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    ex = next(b for b in blocks if "from pointflow import Pipeline" in b)
    assert "__main__" not in ex  # what a new user copies has no guard
    return ex


def _demo_dir(tmp_path: Path) -> Path:
    """A working directory with a small, fast ``configs/demo.yaml`` (cpu tier)."""
    (tmp_path / "configs").mkdir()
    cfg = small_config(supervisor={"max_restarts": 3})
    (tmp_path / "configs" / "demo.yaml").write_text(yaml.safe_dump(cfg))
    return tmp_path


def _check_output(proc: subprocess.CompletedProcess) -> None:
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "bootstrapping phase" not in proc.stderr
    assert "restarting" not in proc.stderr, proc.stderr[-3000:]
    points_in, frames = (int(x) for x in proc.stdout.split()[-2:])
    assert points_in > 0, f"no points reached ingest: {proc.stdout!r}\n{proc.stderr[-3000:]}"


def test_readme_example_runs_as_a_script_without_main_guard(tmp_path):
    cwd = _demo_dir(tmp_path)
    script = cwd / "example.py"
    script.write_text(_readme_python_example())
    proc = subprocess.run([sys.executable, str(script)], cwd=cwd, capture_output=True, text=True, timeout=120)
    _check_output(proc)


def test_readme_example_runs_from_python_c_and_stdin(tmp_path):
    cwd = _demo_dir(tmp_path)
    code = _readme_python_example()
    proc = subprocess.run([sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, timeout=120)
    _check_output(proc)
    # a main with no file at all (an interactive session, a notebook kernel's cell)
    proc = subprocess.run([sys.executable, "-"], input=code, cwd=cwd, capture_output=True, text=True, timeout=120)
    _check_output(proc)


def _sleep_until(pred, timeout: float) -> bool:
    """Wait the way a program with its own loop does: sleeping, never calling poll()/wait()."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.1)
    return bool(pred())


def test_supervision_runs_while_the_caller_only_sleeps(tmp_path):
    cfg = small_config(supervisor={"max_restarts": 3, "restart_backoff_ms": 50})
    pipe = Pipeline.from_dict(cfg, out_dir=str(tmp_path))
    pids = set()
    pipe.start()
    try:
        assert _sleep_until(lambda: pipe.stats()["frames"] >= 2, 60), "stats() never moved while the caller slept"
        for stage in ("ingest", "render"):
            st = pipe.stats()
            old = st["stages"][stage]["pid"]
            pids.update(s["pid"] for s in st["stages"].values())
            frames, points = st["frames"], st["stages"]["ingest"]["points_in"]
            os.kill(old, signal.SIGKILL)
            assert _sleep_until(lambda: pipe.stats()["stages"][stage]["pid"] != old
                                and pipe.stats()["stages"][stage]["alive"], 30), f"{stage} was not restarted"
            assert _sleep_until(lambda: pipe.stats()["frames"] >= frames + 2
                                and pipe.stats()["stages"]["ingest"]["points_in"] > points, 60), \
                "stats() did not advance after the restart"
            assert pipe.stats()["stages"][stage]["restarts"] == 1
        pids.update(s["pid"] for s in pipe.stats()["stages"].values())
    finally:
        final = pipe.stop()
    assert [e["stage"] for e in final["events"]] == ["ingest", "render"]
    assert_gone(pids)
    assert_segments_gone(final)


def _unreported(pipe) -> int:
    st = pipe.stats()
    return st["ring"]["total_written"] - st["stages"]["ingest"]["points_out"]


def _kill_with_unreported_writes(pipe, pid: int, tries: int = 400) -> None:
    """SIGKILL ingest while it is stopped with points in the ring it has not reported."""
    for _ in range(tries):
        try:
            os.kill(pid, signal.SIGSTOP)
            # a report sent before the stop may still be on its way: take two looks
            time.sleep(0.15)
            a = _unreported(pipe)
            time.sleep(0.15)
            if a > 0 and _unreported(pipe) == a:
                os.kill(pid, signal.SIGKILL)  # a stopped process dies too
                return
            os.kill(pid, signal.SIGCONT)
        except ProcessLookupError:
            return  # the supervisor found it frozen and replaced it: a kill all the same
        time.sleep(0.2)
    raise AssertionError("ingest never stopped with unreported writes")


def test_ingest_killed_repeatedly_during_a_replay_accounting_exact(tmp_path):
    """The ring's write counter is the truth: points a killed ingest wrote but never
    reported are reconciled from shared memory (``unreported_written``), including an
    ingest killed just before the stop, which no restart path sees.

    Each kill lands at the precise point, whatever the load: ingest is stopped (SIGSTOP)
    and killed only once the ring holds points it has not reported (the supervisor's view
    of its ``points_out`` stays behind the ring's counter); waiting a fixed 0.7 s and
    hoping it wrote since its last report failed on a loaded machine, where a starved
    ingest may write nothing in that time."""
    rng = np.random.default_rng(3)
    data = np.column_stack([rng.uniform(-20, 20, (400_000, 3)), rng.uniform(0, 1, 400_000)]).astype(np.float32)
    np.save(tmp_path / "cloud.npy", data)
    cfg = small_config(source={"transport": "file", "options": {
                           "path": str(tmp_path / "cloud.npy"), "chunk_points": 5000, "realtime": False,
                           "loop": True}},
                       supervisor={"max_restarts": 10, "restart_backoff_ms": 50, "heartbeat_ms": 1000})
    pipe = Pipeline.from_dict(cfg, out_dir=str(tmp_path / "out"))
    pids = set()
    with pipe:
        for i in range(4):
            written = pipe.stats().get("ring", {}).get("total_written", 0)
            # the (new) ingest has started (a fresh interpreter: seconds on a busy machine) and writes
            pipe.wait(60, until=lambda: pipe.stats()["stages"]["ingest"].get("ready", True)
                      and pipe.stats()["ring"]["total_written"] > written)
            pid = pipe.stats()["stages"]["ingest"]["pid"]
            pids.add(pid)
            _kill_with_unreported_writes(pipe, pid)
            if i < 3:
                pipe.wait(30, until=lambda: pipe.stats()["stages"]["ingest"]["pid"] != pid)
        pids.update(s["pid"] for s in pipe.stats()["stages"].values())
        # the last kill is followed at once by the stop
    final = pipe.stats()
    acc = final["accounting"]
    ing = final["stages"]["ingest"]
    assert acc["ring_written"] == acc["ingest_written"], acc
    assert acc["ring_agrees"] and acc["ingest_balanced"], acc
    assert ing["restarts"] >= 3
    assert ing.get("unreported_written", 0) > 0, "no kill landed between a write and its report?"
    assert acc["ingest_unreported_written"] == ing["unreported_written"]
    assert_gone(pids)
    assert_segments_gone(final)


def test_points_a_source_drops_at_its_send_queue_are_in_the_identities(tmp_path):
    """Issue 19.5: a zmq source receiving faster than ingest takes (ingest frozen) drops
    chunks at its send queue's high-water mark; those points have a named counter and
    the identities hold: received by the sources = forwarded + dropped, forwarded =
    received by ingest."""
    import zmq

    from pointflow import wire
    from pointflow.chunk import PointChunk

    from ..helpers import free_tcp_port

    port = free_tcp_port()
    cfg = small_config(source={"transport": "zmq", "options": {"endpoint": f"tcp://127.0.0.1:{port}",
                                                               "socket": "pull", "bind": True}},
                       ingest={"receive_hwm": 2},
                       supervisor={"hung_after_ms": 30000, "max_restarts": 0})
    pipe = Pipeline.from_dict(cfg, out_dir=str(tmp_path))
    zctx = zmq.Context()
    push = zctx.socket(zmq.PUSH)
    push.setsockopt(zmq.LINGER, 0)
    push.connect(f"tcp://127.0.0.1:{port}")
    rng = np.random.default_rng(5)
    frames = wire.encode(PointChunk(positions=rng.uniform(-5, 5, (5000, 3)).astype(np.float32),
                                    channels={"intensity": rng.uniform(0, 1, 5000).astype(np.float32)}))
    sent = 0
    try:
        with pipe:
            ingest_pid = pipe.stats()["stages"]["ingest"]["pid"]
            os.kill(ingest_pid, signal.SIGSTOP)  # ingest stops taking: the source's queue fills
            try:
                end = time.monotonic() + 3.0
                while time.monotonic() < end:
                    if push.poll(50, zmq.POLLOUT):
                        push.send_multipart(frames, copy=False)
                        sent += 1
            finally:
                os.kill(ingest_pid, signal.SIGCONT)
            # everything the source still holds reaches ingest, then the counts settle (on a
            # loaded machine a starved source can be quiet for seconds: wait for the counts
            # themselves, not for a quiet spell; a loss keeps them apart and fails below)
            def settled() -> bool:
                a = pipe.stats()["accounting"]
                return a["sources_received"] == sent * 5000 and a["sources_forwarded"] == a["ingest_received"] \
                    and a["ingest_balanced"]
            pipe.wait(300, until=settled)
    finally:
        push.close()
        zctx.term()
    acc = pipe.stats()["accounting"]
    assert acc["sources_dropped_by_reason"].get("hwm", 0) > 0, acc  # the load did overflow the queue
    assert acc["sources_received"] == sent * 5000, acc
    assert acc["sources_balanced"], acc
    assert acc["sources_received"] == acc["sources_forwarded"] + acc["sources_dropped"]
    assert acc["lost_before_ingest"] == 0 and acc["sources_forwarded"] == acc["ingest_received"], acc
    assert acc["ingest_balanced"] and acc["ring_agrees"], acc


def test_backoff_starts_again_after_a_healthy_run(tmp_path, monkeypatch):
    """A stage that ran a while before it died restarts after the first backoff again:
    over a long run (the chaos soak kills a stage every 30 s) the backoff must not double
    with every restart of its lifetime; a crash loop still backs off."""
    from pointflow.runtime import supervisor

    monkeypatch.setattr(supervisor, "HEALTHY_S", 1.0)
    cfg = small_config(supervisor={"max_restarts": 10, "restart_backoff_ms": 50})
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path)) as pipe:
        for _ in range(3):
            st = pipe.stats()["stages"]["ingest"]
            pipe.wait(30, until=lambda: pipe.stats()["stages"]["ingest"]["ready"])
            time.sleep(1.5)  # healthy for longer than HEALTHY_S
            pid = pipe.stats()["stages"]["ingest"]["pid"]
            os.kill(pid, signal.SIGKILL)
            pipe.wait(30, until=lambda: pipe.stats()["stages"]["ingest"]["pid"] != pid)
        events = [e for e in pipe.stats()["events"] if e["stage"] == "ingest"]
    assert [e["backoff_ms"] for e in events] == [50, 50, 50], events


def test_a_machine_wide_stall_is_not_a_hang(tmp_path):
    """Every stage silent at once (a loaded machine descheduled them all; seen in the chaos
    soak at load 15-20: four healthy stages killed as "hung" within a second) is not a
    reason to kill them; a single frozen stage among talking ones still is
    (tests/spine/supervision/test_recovery.py::test_a_frozen_stage_is_detected_and_restarted)."""
    # 2.5 x hung_after_ms frozen, well past hung_after_ms but with 2.5 x to spare before the
    # 5 x bound: on a loaded machine the stages need seconds after SIGCONT to talk again
    cfg = small_config(supervisor={"max_restarts": 3, "hung_after_ms": 2000})
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path)) as pipe:
        pipe.wait(60, until=lambda: pipe.stats()["frames"] >= 2)
        pids = [v["pid"] for v in pipe.stats()["stages"].values()]
        for pid in pids:
            os.kill(pid, signal.SIGSTOP)
        try:
            pipe.wait(5.0)
        finally:
            for pid in pids:
                os.kill(pid, signal.SIGCONT)
        frames = pipe.stats()["frames"]
        pipe.wait(30, until=lambda: pipe.stats()["frames"] > frames)
        st = pipe.stats()
    assert st["events"] == [], st["events"]
    assert [v["pid"] for v in st["stages"].values()] == pids
    assert st["frames"] > frames


def test_stages_run_numpy_with_one_blas_thread_unless_the_user_set_one(tmp_path, monkeypatch):
    """A stage is one process doing one thing: BLAS thread pools in every stage would fight
    each other (the frames step ran 2.4x slower with them). A value the user set is kept."""
    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setenv("MKL_NUM_THREADS", "3")
    with Pipeline.from_dict(small_config(), out_dir=str(tmp_path)) as pipe:
        pids = {name: s["pid"] for name, s in pipe.stats()["stages"].items()}
        assert pids
        for name, pid in pids.items():
            env = dict(kv.split("=", 1) for kv in Path(f"/proc/{pid}/environ").read_text().split("\0") if "=" in kv)
            assert env.get("OPENBLAS_NUM_THREADS") == "1" and env.get("OMP_NUM_THREADS") == "1", name
            assert env.get("MKL_NUM_THREADS") == "3", name


def test_a_killed_renderer_is_replaced_by_its_prepared_standby(tmp_path):
    """``supervisor.standby``: each stage has a spare process that has imported its stage
    (the renderer: created its device, drawn a warm-up frame); a restart activates it, and
    a new spare is prepared. Nothing of them is left after the stop."""
    cfg = small_config(supervisor={"max_restarts": 3, "restart_backoff_ms": 50})
    seen = set()
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path)) as pipe:
        def standby(name):
            return pipe.stats()["stages"][name].get("standby_pid")

        for name in ("render", "cadence"):
            spare = _wait(lambda n=name: standby(n), 60)
            assert spare, f"no standby for {name}"
            old = pipe.stats()["stages"][name]["pid"]
            seen.update((old, spare))
            frames = pipe.stats()["frames"]
            os.kill(old, signal.SIGKILL)
            assert _wait(lambda n=name: pipe.stats()["stages"][n]["pid"] == spare and pipe.stats()["stages"][n]["ready"], 60)
            assert _wait(lambda: pipe.stats()["frames"] > frames + 2, 60)
            nxt = _wait(lambda n=name: standby(n), 60)
            assert nxt and nxt != spare
            seen.add(nxt)
        st = pipe.stats()
        assert {e["stage"] for e in st["events"]} == {"render", "cadence"}
        assert _wait(lambda: pipe.stats()["stages"]["ingest"].get("standby_pid"), 60)
        assert _wait(lambda: pipe.stats()["stages"]["source"].get("standby_pid"), 60)
        seen.update(v["standby_pid"] for v in pipe.stats()["stages"].values() if v.get("standby_pid"))
    st = pipe.stats()
    assert_segments_gone(st)
    assert_gone(seen)


def _wait(pred, timeout):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = pred()
        if v:
            return v
        time.sleep(0.1)
    return pred()
