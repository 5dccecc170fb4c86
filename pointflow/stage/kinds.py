"""What a stage kind is: one record per kind, declared next to the stage's own code.

A kind says everything the supervisor and the stage process need to know about a stage:
its loop, the hook a standby runs first, when it starts and stops relative to the others,
whether it gets a standby, which of its stats are running totals, how they enter the
accounting identities, and whether a run with a given config has it. A stage's package
declares it with one call::

    register_stage_kind(StageKind(name="render", main="pointflow.render.process:main",
                                  prepare="pointflow.render.process:prepare",
                                  start_order=10, stop_wave=2, standby=True))

and :data:`KIND_MODULES` below is the one place that lists the modules declaring the
built-in kinds. Hooks are ``"module:function"`` strings, so this module imports no stage
package (imports run one way: the stage packages import the runtime, never the reverse);
the modules are imported on the first lookup. A kind registered from elsewhere (a plugin,
a test) is run like a built-in one.

A *role* (``pointflow run``, ``pointflow send``, ``pointflow router``) is the list of kinds
it runs: the kinds whose :attr:`StageKind.roles` name it.
"""
from __future__ import annotations

import importlib
import threading
from dataclasses import dataclass
from typing import Any, Callable

#: The one registration place: modules that declare the built-in kinds (each calls
#: :func:`register_stage_kind` when imported). Strings, imported on the first lookup.
KIND_MODULES: tuple[str, ...] = (
    "pointflow.ingest.source_process",
    "pointflow.ingest.process",
    "pointflow.cadence.process",
    "pointflow.render.process",
    "pointflow.record.process",
    "pointflow.remote.process",
    "pointflow.remote.router_process",
    "pointflow.map.process",
    "pointflow.serve.process",
)

#: The roles of the command line: ``pointflow run`` (and ``Pipeline``), ``pointflow send``,
#: ``pointflow router``.
ROLES = ("pipeline", "send", "router")


@dataclass(frozen=True)
class StageKind:
    """One stage kind (picklable: the supervisor hands it to the stage process)."""

    name: str                    #: "render"
    main: str                    #: "module:function" of the stage loop, ``fn(ctx: StageContext)``
    prepare: str | None = None   #: "module:function" a standby runs first, ``fn(cfg, info, log) -> object``
    #: Lower starts earlier: downstream first, so each socket a stage connects to is bound
    #: (render 10, cadence 20, recorder 25, ingest 30, sender/router 35, sources 90).
    start_order: int = 50
    #: 0 stops first (sources), then 1 (ingest, sender, router), then 2 (cadence, render, recorder).
    stop_wave: int = 2
    standby: bool = False        #: a prepared spare process takes over on a restart
    #: Stats of this kind that are running totals, summed across restarts (every stage has
    #: ``points_in``, ``points_out`` and the per-reason maps).
    counters: tuple[str, ...] = ()
    #: "module:function" ``fn(stages: dict, ring: dict | None, cfg) -> dict`` merged into
    #: ``stats()["accounting"]`` (``stages``: every stage's stats by name, each with its ``kind``).
    accounting: str | None = None
    #: "module:function" ``fn(cfg) -> bool``: whether a run with this config has the stage
    #: (None: always, in its roles). Called once before anything starts; it may raise
    #: ``ConfigError`` for a config the stage cannot run with (nothing is started then).
    wanted: str | None = None
    #: The roles that run this kind (see :data:`ROLES`).
    roles: tuple[str, ...] = ("pipeline",)
    #: Stages that start later wait until this one reported in (it binds a socket that a
    #: short replay must not miss: the sender).
    await_ready: bool = False


_KINDS: dict[str, StageKind] = {}
_lock = threading.RLock()
_loaded = False


def register_stage_kind(kind: StageKind) -> StageKind:
    """Declare a stage kind (at import of the module that defines the stage). Registering
    the same record again is a no-op; a different record under a taken name is an error."""
    with _lock:
        prev = _KINDS.get(kind.name)
        if prev is not None and prev != kind:
            raise ValueError(f"stage kind {kind.name!r} is already registered ({prev.main})")
        _KINDS[kind.name] = kind
    return kind


def unregister_stage_kind(name: str) -> None:
    """Forget a kind registered at run time (tests)."""
    with _lock:
        _KINDS.pop(name, None)


def _load() -> None:
    global _loaded
    if _loaded:
        return
    with _lock:
        for mod in KIND_MODULES:
            importlib.import_module(mod)
        _loaded = True


def stage_kind(name: str) -> StageKind:
    """The record of kind ``name``; ValueError for an unknown kind."""
    kind = _KINDS.get(name)
    if kind is None:
        _load()
        kind = _KINDS.get(name)
    if kind is None:
        raise ValueError(f"unknown stage kind {name!r} (known: {', '.join(sorted(_KINDS))})")
    return kind


def stage_kinds() -> dict[str, StageKind]:
    """Every registered kind by name, in start order."""
    _load()
    with _lock:
        return {k.name: k for k in sorted(_KINDS.values(), key=lambda k: k.start_order)}


def role_kinds(role: str) -> list[StageKind]:
    """The kinds a role runs, in start order."""
    return [k for k in stage_kinds().values() if role in k.roles]


def resolve(ref: str) -> Callable[..., Any]:
    """The function named by a ``"module:function"`` hook."""
    mod_name, _, fn_name = ref.partition(":")
    return getattr(importlib.import_module(mod_name), fn_name)
