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


BAD_PLUGIN = '''
import numpy as np
from pointflow.chunk import PointChunk
from pointflow.ingest.transports.base import Transport


class Bad(Transport):
    name = "bad"

    def chunks(self):
        good = lambda n: PointChunk(positions=np.zeros((n, 3), np.float32), channels={})
        yield {"x": [1.0]}                                                       # not a chunk
        yield PointChunk(positions=np.zeros((10, 2), np.float32), channels={})   # (n, 2)
        yield good(100)
        yield good(2000)                                                         # over max_chunk_points
        yield PointChunk(positions=np.zeros((5, 3), np.float32), channels={"intensity": np.zeros(4, np.float32)})
        yield good(50)
'''


def test_bad_chunks_from_a_plugin_are_rejected_at_their_source(tmp_path):
    """What a plugin's chunks() yields is checked in the source process: not a PointChunk, a
    wrong shape, too many points, a channel of another length are each rejected there, counted
    by reason and named with the source (they failed later at ingest, with messages that named
    no source, or killed the source); the good chunks between them arrive."""
    (tmp_path / "badplug.py").write_text(BAD_PLUGIN)
    script = tmp_path / "run.py"
    script.write_text(
        "import json\n"
        "from pointflow import Pipeline\n"
        "cfg = {'source': {'transport': 'badplug:Bad', 'name': 'robot'}, 'ingest': {'max_chunk_points': 1000},\n"
        "       'render': {'backend': 'cpu', 'size': [64, 48]}}\n"
        "with Pipeline.from_dict(cfg, out_dir='') as p:\n"
        "    p.wait(60, until=lambda: p.stats()['stages']['ingest']['points_out'] >= 150)\n"
        "    p.wait(2)\n"
        "    st = p.stats()\n"
        "print(json.dumps({'src': st['stages']['robot'], 'ingest': st['stages']['ingest']['points_out'],\n"
        "                  'events': [e['action'] for e in st['events']]}))\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    r = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True, timeout=180, env=env)
    assert r.returncode == 0, r.stderr[-3000:]
    import json

    out = json.loads(r.stdout.strip().splitlines()[-1])
    src = out["src"]
    assert out["ingest"] == 150 and out["events"] == [], out
    assert src["transport_rejected"] == 4, src
    for reason in ("bad_chunk", "bad_positions", "too_large", "length_mismatch"):
        assert src[f"transport_rejected_{reason}"] == 1, (reason, src)
    lines = [ln for ln in r.stderr.splitlines() if "rejected message" in ln]
    assert len(lines) == 4 and all("robot: rejected message [" in ln for ln in lines), r.stderr[-3000:]
    assert any("yielded a dict, expected a PointChunk" in ln for ln in lines)
    assert any("ingest.max_chunk_points" in ln for ln in lines)
    assert "Traceback" not in r.stderr


def test_a_plugin_class_without_chunks_is_refused_at_load(tmp_path, monkeypatch):
    """A Transport subclass that does not define chunks() validated and then failed in every
    start of its stage (three restarts); it is refused at load, naming what it lacks."""
    (tmp_path / "nochunks_plug.py").write_text(
        "from pointflow.ingest.transports.base import Transport\n\nclass NoChunks(Transport):\n    name = 'nochunks'\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ConfigError, match=r"nochunks_plug:NoChunks does not define chunks\(\)"):
        load_config({"source": {"transport": "nochunks_plug:NoChunks"}})


def test_a_plugin_in_the_working_directory_gets_a_hint(tmp_path, monkeypatch):
    """`pointflow run` does not import from the working directory: a dotted-path plugin there
    is not found, and the error says why and what to do."""
    (tmp_path / "cwdplug.py").write_text("from pointflow.ingest.transports.base import Transport\n")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError, match=r"No module named 'cwdplug' \(it is in the working directory.*PYTHONPATH=\."):
        load_config({"source": {"transport": "cwdplug:T"}})


def test_a_plugin_stuck_in_chunks_is_said(monkeypatch, caplog):
    """A plugin's chunks() that blocks (or open() that does not return) kept the stage alive
    and silent until --duration ended; the source process's watch says it once per call."""
    import logging
    import time

    from pointflow.ingest import source_process as sp

    monkeypatch.setattr(sp, "STALL_S", 1.0)
    log = logging.getLogger("test.stall")
    w = sp._StallWatch(log, "robot", "myplug:Slow")
    try:
        with caplog.at_level(logging.WARNING, logger="test.stall"):
            w.enter("chunks()")
            time.sleep(0.3)
            w.leave()                       # a quick call: nothing said
            w.enter("chunks()")
            end = time.monotonic() + 10
            while not caplog.records and time.monotonic() < end:
                time.sleep(0.1)
            time.sleep(1.5)                 # still the same call: said once
            w.leave()
        msgs = [r.getMessage() for r in caplog.records]
        assert len(msgs) == 1, msgs
        assert msgs[0].startswith("source 'robot': transport myplug:Slow: chunks() has not yielded for ")
        assert "yield None while idle" in msgs[0]
    finally:
        w.close()


def test_options_to_a_plugin_that_takes_none_say_so(tmp_path, monkeypatch):
    """An option given to a plugin without options_schema said 'expected one of ' and nothing."""
    (tmp_path / "noopt_plug.py").write_text(
        "from pointflow.ingest.transports.base import Transport\n\nclass T(Transport):\n"
        "    def chunks(self):\n        yield None\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ConfigError, match=r"sources\[0\]\.options\.a: unknown key 'a'; sources\[0\]\.options takes no keys"):
        load_config({"source": {"transport": "noopt_plug:T", "options": {"a": 1}}})
