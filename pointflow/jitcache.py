"""numba's on-disk cache of pointflow's compiled loops: is it filled, and filling it in a
process of its own.

Why: compiling the cpu raster's loops takes ~18 s on an idle 2-core machine (30-50 s under
load). A stage that compiled them itself would draw nothing for that long, and a run
stopped mid-compile would leave nothing cached, so the next run starts over. Instead a stage
asks :func:`state` (reads numba's index files, compiles nothing), draws with what is ready,
and :func:`start_compiler` fills the cache beside it in a detached process
(``python -m pointflow.jitcache MODULE:FUNCTION``) that outlives the run if it must.

A killed compiler leaves no broken cache: it writes each data file before the index entry
that names it, under a fresh name, both by write-then-rename (numba itself writes the index
first, so a kill between the two could point an entry at an old file of the same name).
Left-over ``*.tmp.*`` files of a killed compiler are removed by the next one. One compiler
per cache directory at a time (an ``flock`` on ``pointflow-compile.lock`` there).

Imports nothing of pointflow but what the caller names, so every layer may use it.
"""
from __future__ import annotations

import fcntl
import glob
import importlib
import itertools
import json
import os
import subprocess
import sys
import time
from typing import Any, Iterable, Optional

#: the lock file (held by the compiler while it works) and its result, in the cache directory
LOCK_NAME = "pointflow-compile.lock"
STATUS_NAME = "pointflow-compile.json"
#: the compiler runs below the stages' priority: the picture comes first
COMPILER_NICE = 5

READY, MISSING, UNWRITABLE = "ready", "missing", "unwritable"


def cache_dir(dispatchers: Iterable[Any]) -> Optional[str]:
    """The directory numba caches these dispatchers in, or None (caching off: no writable place)."""
    for d in dispatchers:
        path = getattr(getattr(d, "_cache", None), "cache_path", None)
        if path:
            return str(path)
    return None


def _magic_tuple() -> Any:
    from numba.core.registry import cpu_target

    return cpu_target.target_context.codegen().magic_tuple()


def state(dispatchers: Iterable[Any]) -> str:
    """:data:`READY` when every dispatcher's index holds an entry for this machine whose data
    file exists (loading them compiles nothing), :data:`MISSING` when one lacks it,
    :data:`UNWRITABLE` when numba has no cache for them (no writable location)."""
    ds = list(dispatchers)
    if not ds or cache_dir(ds) is None:
        return UNWRITABLE
    try:
        magic = _magic_tuple()
        for d in ds:
            f = d._cache._cache_file
            entries = f._load_index()
            if not any(k[1] == magic and os.path.exists(f._data_path(name)) for k, name in entries.items()):
                return MISSING
    except Exception:  # noqa: BLE001 - an index numba itself would not load: not ready
        return MISSING
    return READY


def _lock_path(where: str) -> str:
    return os.path.join(where, LOCK_NAME)


def compiling(where: str) -> bool:
    """True while a compiler holds the lock of cache directory ``where``."""
    try:
        fd = os.open(_lock_path(where), os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        return False
    except OSError:
        return True
    finally:
        os.close(fd)


def last_result(where: str) -> Optional[dict]:
    """What the last compiler of ``where`` said: ``{"ok", "message", "seconds", "pid"}`` or None."""
    try:
        with open(os.path.join(where, STATUS_NAME)) as f:
            d = json.load(f)
        return d if isinstance(d, dict) else None
    except (OSError, ValueError):
        return None


def start_compiler(target: str, where: str) -> subprocess.Popen:
    """Start ``python -m pointflow.jitcache target`` detached (own session: a Ctrl-C or the
    stop of the stage that started it does not cut it short), below the stages' priority.
    ``target`` is ``module:function``, a function that compiles every loop (:func:`main`)."""
    env = dict(os.environ)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return subprocess.Popen([sys.executable, "-m", "pointflow.jitcache", target], env=env,
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True, close_fds=True)


def _save_data_first(self, key, data) -> None:
    """numba's ``IndexDataCacheFile.save`` with the data file written (under a name no file
    has) before the index entry that names it: a kill at any point leaves an index whose
    every entry is complete."""
    overloads = self._load_index()
    taken = set(overloads.values())
    for i in itertools.count(1):
        name = self._data_name(i)
        if name not in taken and not os.path.exists(self._data_path(name)):
            break
    self._save_data(name, data)
    overloads = self._load_index()  # as it is now
    overloads[key] = name
    self._save_index(overloads)


def safe_saves() -> bool:
    """Make numba's cache writes in this process data-first (:func:`_save_data_first`).
    False when numba's cache file class is not the shape this was written for (then numba's
    own order is kept)."""
    from numba.core import caching

    cls = getattr(caching, "IndexDataCacheFile", None)
    need = ("_load_index", "_save_index", "_save_data", "_data_name", "_data_path", "save")
    if cls is None or not all(hasattr(cls, n) for n in need):
        return False
    cls.save = _save_data_first
    return True


def _sweep_tmp(where: str) -> int:
    """Remove half-written files a killed writer left (``<file>.tmp.<uid>``); the lock is held."""
    n = 0
    for p in glob.glob(os.path.join(where, "*.tmp.*")):
        try:
            os.unlink(p)
            n += 1
        except OSError:
            pass
    return n


def _write_status(where: str, d: dict) -> None:
    tmp = os.path.join(where, f"{STATUS_NAME}.{os.getpid()}")
    with open(tmp, "w") as f:
        json.dump(d, f)
    os.replace(tmp, os.path.join(where, STATUS_NAME))


def run(target: str, progress=None) -> dict:
    """Compile every loop of ``target`` (``module:function``; the function returns the
    dispatchers it compiled) into numba's cache, holding the directory's lock.
    Returns ``{"ok", "message", "seconds", "where"}``; ``where`` None: nothing can be cached."""
    mod, _, fn = target.partition(":")
    t0 = time.monotonic()
    safe_saves()
    func = getattr(importlib.import_module(mod), fn)
    where = func(dispatchers_only=True)
    where = cache_dir(where)
    if where is None:
        return {"ok": False, "message": "numba has no writable cache location (set NUMBA_CACHE_DIR)",
                "seconds": 0.0, "where": None}
    fd = os.open(_lock_path(where), os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            if progress:
                progress("another compiler is filling this cache; waiting for it")
            fcntl.flock(fd, fcntl.LOCK_EX)
        _sweep_tmp(where)
        try:
            ds = func(dispatchers_only=True)
            if state(ds) != READY:
                func(dispatchers_only=False)
            ok = state(ds) == READY
            msg = "compiled" if ok else "compiled, but the cache did not take it (disk full or not writable?)"
        except Exception as exc:  # noqa: BLE001 - said by the caller, once
            ok, msg = False, f"{type(exc).__name__}: {exc}"
        res = {"ok": ok, "message": msg, "seconds": round(time.monotonic() - t0, 2), "pid": os.getpid(),
               "where": where}
        try:
            _write_status(where, res)
        except OSError as exc:
            res.update(ok=False, message=f"{msg}; status not writable ({exc})")
        return res
    finally:
        os.close(fd)  # releases the lock


def main(argv: Optional[list[str]] = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1 or ":" not in args[0]:
        print("usage: python -m pointflow.jitcache MODULE:FUNCTION", file=sys.stderr)
        return 2
    try:
        os.nice(COMPILER_NICE)  # here, not in a preexec_fn: the stage starting it has threads
    except OSError:
        pass
    res = run(args[0])
    return 0 if res["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())


#: every compiled loop of pointflow: (what, ``module:function``) for :func:`warm_all`
TARGETS = (("the cpu raster", "pointflow.render.cpu_compute:compile_all"),
           ("the frames transform", "pointflow.frames.compiled:compile_all"))


def warm_all(progress) -> bool:
    """Compile every loop of :data:`TARGETS` into numba's cache (``pointflow warm``), saying
    each step through ``progress(line)``. True when all are cached."""
    ok = True
    for what, target in TARGETS:
        mod, _, fn = target.partition(":")
        try:
            ds = getattr(importlib.import_module(mod), fn)(dispatchers_only=True)
        except Exception as exc:  # noqa: BLE001 - numba missing or broken
            progress(f"{what}: skipped: {type(exc).__name__}: {exc}")
            continue
        if not ds:
            progress(f"{what}: skipped: numba is not installed or POINTFLOW_NO_NUMBA is set")
            continue
        where = cache_dir(ds)
        if state(ds) == READY:
            progress(f"{what}: already compiled for this machine ({where})")
            continue
        if where is None:
            progress(f"{what}: numba has no writable cache location: set NUMBA_CACHE_DIR to a writable directory")
            ok = False
            continue
        progress(f"{what}: compiling for this machine into {where} (once; about 20 s on 2 idle cores) ...")
        res = run(target, progress)
        progress(f"{what}: {res['message']} in {res['seconds']:.1f} s" if res["ok"] else f"{what}: failed: {res['message']}")
        ok = ok and bool(res["ok"])
    return ok
