"""Suite-wide set-up: a private XDG_RUNTIME_DIR (silences wgpu/Mesa warnings, holds ipc:// sockets)."""
import os
import tempfile

import pytest

if not os.environ.get("XDG_RUNTIME_DIR"):
    d = os.path.join(tempfile.gettempdir(), f"pointflow-xdg-{os.getuid()}")
    os.makedirs(d, mode=0o700, exist_ok=True)
    os.environ["XDG_RUNTIME_DIR"] = d


def pytest_sessionstart(session):
    """Compile the cpu tier's numba loops once, into numba's disk cache: on a fresh clone a
    render stage choosing the compiled cpu raster (``backend: auto`` over a software adapter)
    would otherwise compile them inside its start-up grace period; later loads take ~0.5 s."""
    try:
        from pointflow.render import cpu_kernels

        cpu_kernels.load()
    except Exception:  # noqa: BLE001 - no numba: the reference tier draws, nothing to warm
        pass


#: Test files that load the machine on purpose (busy loops), run links between network
#: namespaces whose heartbeats are the subject, or drive a browser. Under ``pytest -n 2
#: --dist loadfile`` (``make test``) the files of one group run on one worker, one test at a
#: time, so two of them never stack their load (or two browsers) on the two cores; any other
#: file may run beside one of them (each test holds under load: it waits on conditions, not
#: times).
GROUPS = {"tests/remote/test_links.py": "heavy", "tests/remote/test_ros2_zenoh_netns.py": "heavy",
          "tests/remote/test_sigterm.py": "heavy", "tests/remote/test_zenoh_topologies.py": "heavy",
          "tests/spine/test_hung_under_load.py": "heavy", "tests/spine/test_startup_under_load.py": "heavy",
          "tests/notebook/test_jupyterlab.py": "browser", "tests/serve/test_browser.py": "browser"}


@pytest.hookimpl(optionalhook=True, tryfirst=True)
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadfile``: each file's tests on one worker (a module-scoped fixture, e.g. a
    pipeline its tests share, starts once), and the files of a :data:`GROUPS` group on one
    worker. (xdist's own ``loadgroup`` marks do not reach its scheduler under pytest 9: it
    renames ``item._nodeid``, which pytest 9 no longer reads.)"""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class FileGroups(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            path = super()._split_scope(nodeid)
            return GROUPS.get(path, path)

    return FileGroups(config, log)
