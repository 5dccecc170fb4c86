"""A stage kind is one record (pointflow/stage/kinds.py): the supervisor starts, stops,
restarts, counts and accounts a kind declared in a test module like a built-in one, and
the built-in kinds say what docs/architecture.md says (start order, stop waves, roles)."""
from __future__ import annotations

import os
import signal

import pytest

from pointflow import Pipeline
from pointflow.stage.kinds import StageKind, register_stage_kind, role_kinds, stage_kind, stage_kinds

from .. import probe_stage
from ..helpers import assert_gone, assert_segments_gone, small_config, wait_for


@pytest.fixture
def probe(monkeypatch):
    # the stage's own process must import the probe's module by name
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(p for p in (probe_stage.import_root(),
                                                                 os.environ.get("PYTHONPATH")) if p))
    monkeypatch.setattr(probe_stage, "WANTED", True)
    probe_stage.register()
    try:
        yield probe_stage
    finally:
        probe_stage.unregister()


def test_builtin_kinds_and_roles():
    kinds = stage_kinds()
    assert {"source", "ingest", "cadence", "render", "recorder", "sender", "router", "map"} <= set(kinds)
    assert [k.name for k in role_kinds("pipeline")] == ["render", "map", "cadence", "recorder", "ingest", "serve",
                                                       "source"]
    assert [k.name for k in role_kinds("send")] == ["sender", "source"]
    assert [k.name for k in role_kinds("router")] == ["router"]
    # upstream stops first: sources, then ingest / sender / router, then the rest
    assert stage_kind("source").stop_wave < stage_kind("ingest").stop_wave < stage_kind("render").stop_wave
    assert stage_kind("sender").stop_wave == stage_kind("router").stop_wave == stage_kind("ingest").stop_wave
    assert {k.name for k in kinds.values() if k.standby} == {"render", "cadence", "ingest", "source"}
    assert stage_kind("render").prepare and stage_kind("ingest").prepare
    with pytest.raises(ValueError, match="unknown stage kind 'nope'"):
        stage_kind("nope")


def test_stage_entry_files_are_named_one_way():
    """A kind's loop lives in its package's process.py, or <kind>_process.py for a second
    stage in the same package, and that file declares the kind (issue 27.4)."""
    import importlib

    for kind in stage_kinds().values():
        mod = kind.main.partition(":")[0]
        if not mod.startswith("pointflow."):
            continue
        assert mod.rpartition(".")[2] in ("process", f"{kind.name}_process"), kind
        assert getattr(importlib.import_module(mod), "KIND", None) == kind, f"{mod} does not declare {kind.name}"


def test_a_taken_name_is_refused():
    with pytest.raises(ValueError, match="stage kind 'render' is already registered"):
        register_stage_kind(StageKind(name="render", main="elsewhere:main"))
    assert register_stage_kind(stage_kind("render")) is not None  # the same record again: a no-op


def test_a_kind_from_a_test_module_is_run_like_a_builtin(tmp_path, probe):
    """Registered from here, nothing in pointflow edited: started in its start order,
    its counters carried over a restart, its identities in the accounting, stopped and
    gone at the end."""
    cfg = small_config(supervisor={"max_restarts": 2, "restart_backoff_ms": 50})
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path)) as pipe:
        assert list(pipe.stats()["stages"])[:3] == ["render", "probe", "cadence"]  # start_order 15
        assert wait_for(lambda: pipe.stats()["stages"]["probe"]["probe_ticks"] >= 5, 60)
        st = pipe.stats()["stages"]["probe"]
        assert st["kind"] == "probe" and st["ready"], st
        before, pid = st["probe_ticks"], st["pid"]
        os.kill(pid, signal.SIGKILL)
        assert wait_for(lambda: pipe.stats()["stages"]["probe"]["pid"] != pid
                        and pipe.stats()["stages"]["probe"]["ready"], 60)
        assert wait_for(lambda: pipe.stats()["stages"]["probe"]["probe_ticks"] > before, 60)
        st = pipe.stats()["stages"]["probe"]
        assert st["restarts"] == 1, st
        # a running total carries the dead incarnation's count; a gauge shows the live one's
        assert st["probe_ticks"] > before and st["probe_pid_gauge"] == st["pid"] != pid, st
        acc = pipe.stats()["accounting"]
        assert acc["probe_balanced"] and acc["probe_ticks"] > before, acc
        assert acc["ingest_balanced"], acc  # the built-in identities are still there
        pids = [s["pid"] for s in pipe.stats()["stages"].values()]
    final = pipe.stats()
    assert final["stages"]["probe"]["alive"] is False
    assert final["accounting"]["probe_balanced"], final["accounting"]
    assert_gone(pids)
    assert_segments_gone(final)


def test_a_kind_the_config_does_not_want_is_not_started(tmp_path, probe, monkeypatch):
    monkeypatch.setattr(probe_stage, "WANTED", False)
    with Pipeline.from_dict(small_config(), out_dir=str(tmp_path)) as pipe:
        stats = pipe.stats()
    assert "probe" not in stats["stages"] and "probe_ticks" not in stats["accounting"], stats
