"""Suite-wide set-up: a private XDG_RUNTIME_DIR (silences wgpu/Mesa warnings, holds ipc:// sockets)."""
import os
import tempfile

import pytest

if not os.environ.get("XDG_RUNTIME_DIR"):
    d = os.path.join(tempfile.gettempdir(), f"pointflow-xdg-{os.getuid()}")
    os.makedirs(d, mode=0o700, exist_ok=True)
    os.environ["XDG_RUNTIME_DIR"] = d


def pytest_sessionstart(session):
    """Compile pointflow's numba loops once, into numba's disk cache (``pointflow warm``): a
    stage whose loops are not cached draws (or places points) without them while a compiler
    fills the cache beside it, and the tests of the compiled paths want them from the start.
    ~20 s the first time on a machine, a fraction of a second after."""
    try:
        from pointflow.jitcache import warm_all

        warm_all(lambda line: None)
    except Exception:  # noqa: BLE001 - no numba: the reference tier draws, nothing to warm
        pass


#: Test files that load the machine on purpose (busy loops), run links (between network
#: namespaces, over Zenoh) whose heartbeats and queues are the subject, or drive a browser.
#: Under ``pytest -n 2 --dist loadfile`` (``make test``) the files of one group run on one
#: worker, one test at a time, so two of them never stack their load (or two browsers) on
#: the two cores; any other file may run beside one of them (each test holds under load: it
#: waits on conditions, not times). Every file under ``tests/remote/`` is in "heavy": beside
#: each other, at load 7-15, four of them failed (slow-receiver and refusal waits).
GROUPS = {"tests/spine/supervision/test_hung_under_load.py": "heavy", "tests/spine/supervision/test_startup_under_load.py": "heavy",
          "tests/startup/test_compile_beside.py": "heavy",  # compiles from empty caches: minutes of both cores
          "tests/notebook/test_jupyterlab.py": "browser", "tests/serve/test_browser.py": "browser",
          "tests/serve/test_page_overlay.py": "browser",
          "tests/serve/test_link_browser.py": "browser",
          "tests/notebook/test_widget_controls.py": "browser",
          # one package-scoped pipeline (tests/serve/conftest.py: hostile_pipe) serves both
          "tests/serve/test_hostile.py": "hostile", "tests/serve/test_attacks.py": "hostile"}
HEAVY_DIRS = ("tests/remote/",)


def file_group(path: str) -> str:
    """The xdist work unit of a test file (its path relative to the repository)."""
    return "heavy" if path.startswith(HEAVY_DIRS) else GROUPS.get(path, path)


def pytest_collection_modifyitems(config, items):
    """Under xdist, the "heavy" group first: its files run one after another on one worker,
    the longest unit of the run, so it must not start last."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    root = str(config.rootpath)
    items.sort(key=lambda it: file_group(os.path.relpath(str(it.path), root)) != "heavy")  # stable


@pytest.hookimpl(optionalhook=True, tryfirst=True)
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadfile``: each file's tests on one worker (a module-scoped fixture, e.g. a
    pipeline its tests share, starts once), and the files of a group (:func:`file_group`) on
    one worker. (xdist's own ``loadgroup`` marks do not reach its scheduler under pytest 9: it
    renames ``item._nodeid``, which pytest 9 no longer reads.)"""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class FileGroups(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return file_group(super()._split_scope(nodeid))

    return FileGroups(config, log)
