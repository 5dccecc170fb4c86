"""A stage process's entry: start-up, stop signals, logging, the loop, the way out.

The supervisor (or :mod:`.launch`, :mod:`.forkserver`) runs :func:`stage_main` in a fresh
process; it loads the config, builds the stage's :class:`~pointflow.stage.StageContext`
(the stage kit, :mod:`pointflow.stage`) and runs its kind's loop.
"""
from __future__ import annotations

import ctypes
import importlib
import logging
import os
import signal
import sys
import time
import traceback
from typing import Any

from ..config import load_config
from ..errors import to_fields
from ..stage.context import RunInfo, StageContext
from ..stage.kinds import StageKind, resolve, stage_kind


def _die_with_parent() -> None:
    """Linux: get SIGTERM if the supervisor dies, so no stage outlives it."""
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


def _setup_logging(name: str, info: RunInfo, standby: bool = False) -> None:
    """Log lines that name the stage; a standby's say ``<name>-standby`` (its tier selection
    and warm-up are a spare being prepared, not a restart), until it is activated."""
    from ..stage.console import setup_logging  # on a terminal, a log line clears the progress line first

    global _standby_handlers
    fmt = f"%(asctime)s {name}{'-standby' if standby else ''}[%(process)d] %(levelname)s %(message)s"
    if _standby_handlers and not standby:  # a standby activated: its own handlers, the stage's label
        for h in _standby_handlers:
            h.setFormatter(type(h.formatter)(fmt) if h.formatter is not None else logging.Formatter(fmt))
        _standby_handlers = []
        return
    setup_logging(info.log_level, fmt)
    if standby:
        _standby_handlers = list(logging.getLogger().handlers)


#: The log handlers a standby set up (relabelled when it is activated).
_standby_handlers: list[logging.Handler] = []


def _kind(kind: str | StageKind) -> StageKind:
    """The supervisor hands the record itself, so a stage process imports only its own
    module; a name (a test starting a stage directly) is looked up."""
    return kind if isinstance(kind, StageKind) else stage_kind(kind)


def prepare_stage(name: str, kind: str | StageKind, cfg_dict: dict, base_dir: str, info: RunInfo) -> Any:
    """A standby's head start, before it is needed: import the stage's module and run its
    kind's ``prepare`` hook. Nothing here binds a socket or talks to the supervisor (the
    incarnation it replaces may still be alive). Returns what the hook returned (None when
    it failed: the stage then does the work itself)."""
    _setup_logging(name, info, standby=True)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    log = logging.getLogger(f"pointflow.{name}")
    try:
        k = _kind(kind)
        importlib.import_module(k.main.partition(":")[0])
        if k.prepare is None:
            return None
        log.info("preparing a standby: a spare %s that takes over if the running one dies (supervisor.standby)",
                 name)
        cfg = load_config(cfg_dict, base_dir=base_dir)
        return resolve(k.prepare)(cfg, info, log)
    except Exception as exc:  # noqa: BLE001 - the activated stage does it again and reports
        log.warning("standby %s: preparing failed (%s); the stage will start from scratch", name, exc)
        return None


def stage_main(name: str, kind: str | StageKind, cfg_dict: dict, base_dir: str, info: RunInfo,
               prepared: Any = None) -> None:
    """Process entry point (:mod:`.launch` runs it in a fresh interpreter)."""
    _die_with_parent()
    _setup_logging(name, info)
    # Ctrl-C reaches the whole process group; only the supervisor reacts to it and then
    # stops the stages in order.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    t_imports = time.monotonic_ns()
    cfg = load_config(cfg_dict, base_dir=base_dir)
    k = _kind(kind)
    loop = resolve(k.main)  # the stage's own module (its tier's libraries come later, in its loop)
    t_module = time.monotonic_ns()
    ctx = StageContext(name, k.name, cfg, info)
    ctx.prepared = prepared
    signal.signal(signal.SIGTERM, lambda *_: ctx.stop())
    # where this stage's start went, before its loop sets up (``stats()["stages"][s]["startup_ms"]``)
    ctx._send({"type": "starting", "marks_ns": {"main": info.extra.get("t_main_ns", t_imports),
                                                "runtime": t_imports, "module": t_module,
                                                "context": time.monotonic_ns()}})
    code = 0
    try:
        loop(ctx)
        if ctx._running:  # returned on its own
            ctx.input_ended()
    except Exception as exc:  # noqa: BLE001 - report, then exit non-zero
        # the supervisor prints the last line with the stage's exit (once); here only when it
        # cannot be told, or as the whole traceback with -v
        if not ctx.report_error("".join(traceback.format_exception(exc)), to_fields(exc)):
            ctx.log.error("stage failed: %s", exc)
        ctx.log.debug("stage failed", exc_info=True)
        code = 1
    finally:
        ctx.close()
        if os.getppid() != info.parent:
            # the supervisor was killed and could not unlink its segments: do it for it
            from ..ring.sweep import sweep_orphans

            for name in sweep_orphans():
                logging.getLogger("pointflow").warning("removed %s (its supervisor is gone)", name)
            from .rundir import remove_orphaned_run_dir

            if remove_orphaned_run_dir(info.run_dir, info.supervisor_pid):
                logging.getLogger("pointflow").warning("removed %s (its supervisor is gone)", info.run_dir)
    sys.exit(code)
