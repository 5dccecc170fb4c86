"""Suite-wide set-up: a private XDG_RUNTIME_DIR (silences wgpu/Mesa warnings, holds ipc:// sockets)."""
import os
import tempfile

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


#: Test files that load the machine on purpose (busy loops), run links between network
#: namespaces whose heartbeats are the subject, or drive a browser. Under ``pytest -n 2
#: --dist loadgroup`` (``make test``) the files of one group run on one worker, one test at
#: a time, so two of them never stack their load (or two browsers) on the two cores; any
#: other file may run beside one of them (each test holds under load: it waits on
#: conditions, not times).
GROUPS = {"tests/remote/test_links.py": "heavy", "tests/remote/test_ros2_zenoh_netns.py": "heavy",
          "tests/remote/test_sigterm.py": "heavy", "tests/remote/test_zenoh_topologies.py": "heavy",
          "tests/spine/test_hung_under_load.py": "heavy", "tests/spine/test_startup_under_load.py": "heavy",
          "tests/notebook/test_jupyterlab.py": "browser", "tests/serve/test_browser.py": "browser"}


def pytest_collection_modifyitems(config, items):
    """Every test is in an xdist group: its file's (so a module-scoped fixture, e.g. a
    pipeline shared by a file's tests, starts once, on one worker), or its file's entry in
    :data:`GROUPS`. Without ``-n`` the marks change nothing."""
    import pytest

    root = str(config.rootpath)
    for item in items:
        rel = os.path.relpath(str(item.path), root)
        item.add_marker(pytest.mark.xdist_group(GROUPS.get(rel, rel)))
