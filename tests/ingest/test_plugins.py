"""The example plugin package, installed into the venv, run in a real pipeline from its
entry point and from its dotted path; plugin errors name the plugin and the cause."""
import os
import subprocess
import sys

import pytest

from pointflow.config import ConfigError, load_config

EXAMPLE = os.path.join(os.path.dirname(__file__), "..", "..", "examples", "pointflow-plugin-example")


@pytest.fixture(scope="module")
def installed_plugin():
    r = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-build-isolation", "-q", "-e",
                        os.path.abspath(EXAMPLE)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    import importlib
    import site

    importlib.invalidate_caches()
    for d in site.getsitepackages():  # pick up the editable finder's .pth in this process
        site.addsitedir(d)
    yield
    subprocess.run([sys.executable, "-m", "pip", "uninstall", "-y", "-q", "pointflow-plugin-example"],
                   capture_output=True, timeout=300)


def _run(transport, tmp_path):
    from pointflow import Pipeline

    cfg = {"source": {"transport": transport, "options": {"points_per_chunk": 1000, "chunks": 12, "rate": 0}},
           "ring": {"max_points": 100_000},
           "render": {"backend": "cpu", "size": [160, 120], "output": {"dir": None}}}
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path)) as p:
        p.wait(30, until=lambda: p.stats()["stages"].get("ingest", {}).get("points_out", 0) >= 12_000)
        stats = p.stats()
    return stats


def test_plugin_from_entry_point(installed_plugin, tmp_path):
    from pointflow.ingest.transports import available_transports

    assert "helix" in available_transports()
    stats = _run("helix", tmp_path)
    assert stats["stages"]["ingest"]["points_out"] == 12_000
    assert stats["stages"]["source"]["points_out"] == 12_000


def test_plugin_from_dotted_path(installed_plugin, tmp_path):
    stats = _run("pointflow_plugin_example.helix:HelixTransport", tmp_path)
    assert stats["stages"]["ingest"]["points_out"] == 12_000


def test_plugin_option_rejection_names_the_key(installed_plugin):
    with pytest.raises(ConfigError, match=r"sources\[0\]\.options\.radius.*must be > 0.*transport 'helix'"):
        load_config({"source": {"transport": "helix", "options": {"radius": -1}}})
    with pytest.raises(ConfigError, match=r"sources\[0\]\.options\.colour.*unknown key"):
        load_config({"source": {"transport": "helix", "options": {"colour": 1}}})


def test_plugin_import_failure_names_plugin_and_cause():
    with pytest.raises(ConfigError) as e:
        load_config({"source": {"transport": "no_such_pkg.mod:Thing"}})
    msg = str(e.value)
    assert "sources[0].transport" in msg and "no_such_pkg.mod" in msg and "ModuleNotFoundError" in msg
    with pytest.raises(ConfigError, match="has no attribute 'Nope'"):
        load_config({"source": {"transport": "pointflow.ingest.transports.synthetic:Nope"}})
    with pytest.raises(ConfigError, match="not a pointflow Transport subclass"):
        load_config({"source": {"transport": "pointflow.chunk:PointChunk"}})
