"""A stage kind declared outside pointflow, for tests/spine/house/test_stage_kinds.py: what a new
stage's package holds (its loop, its identities, whether a config wants it), registered
with one call (:func:`register`), nothing else edited."""
from __future__ import annotations

import os
import sys

from pointflow.stage.kinds import StageKind, register_stage_kind, unregister_stage_kind

#: Whether a run has the probe (read by :func:`wanted` in the supervisor's process).
WANTED = True


def main(ctx) -> None:
    """Counts its loops as points in and out; ``probe_ticks`` is a running total."""
    while ctx.running:
        ctx.counters.points_in += 1
        ctx.counters.points_out += 1
        ctx.counters.extra["probe_ticks"] = ctx.counters.points_in
        ctx.counters.extra["probe_pid_gauge"] = os.getpid()
        ctx.beat()
        ctx.sleep(0.02)


def identities(stages: dict, ring, cfg) -> dict:
    probe = stages.get("probe", {})
    return {"probe_ticks": probe.get("probe_ticks", 0),
            "probe_balanced": probe.get("points_in", 0) == probe.get("points_out", 0)}


def wanted(cfg) -> bool:
    return WANTED


KIND = StageKind(name="probe", main=f"{__name__}:main", start_order=15, stop_wave=2, counters=("probe_ticks",),
                 accounting=f"{__name__}:identities", wanted=f"{__name__}:wanted")


def import_root() -> str:
    """The directory a fresh interpreter needs on its path to import this module by name."""
    path = os.path.abspath(sys.modules[__name__].__file__)
    for _ in __name__.split("."):
        path = os.path.dirname(path)
    return path


def register() -> StageKind:
    return register_stage_kind(KIND)


def unregister() -> None:
    unregister_stage_kind(KIND.name)


def fail_keyed(ctx) -> None:
    """A stage whose loop raises a keyed error, for tests/spine/house/test_errors.py."""
    from pointflow.config import ConfigError

    ctx.beat(force=True)
    raise ConfigError("probe.option", "refused by the probe stage")


KEYED = StageKind(name="keyed_probe", main=f"{__name__}:fail_keyed", start_order=16, stop_wave=2)
