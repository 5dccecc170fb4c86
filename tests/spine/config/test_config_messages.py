"""Each config error names the key path and the valid values (issue 22, item 1): inside an
optional block (``send:``) too, where the Union conversion used to swallow the inner error."""
import pytest

from pointflow.cli import main
from pointflow.config import ConfigError, load_config

BASE = {"source": {"transport": "synthetic"}}


def _err(extra: dict) -> ConfigError:
    with pytest.raises(ConfigError) as ei:
        load_config({**BASE, **extra})
    return ei.value


@pytest.mark.parametrize("send,path,must_say", [
    ({"compression": "gzip"}, "send.compression", ["none", "lz4", "zstd", "'gzip'"]),
    ({"socket": "dealer"}, "send.socket", ["pub", "push", "'dealer'"]),
    ({"compresion": "lz4"}, "send.compresion", ["unknown key 'compresion'", "did you mean 'compression'",
                                                "endpoint", "socket", "send_hwm"]),
    ({"send_hwm": "many"}, "send.send_hwm", ["expected an integer", "'many'"]),
    ({"send_hwm": 0}, "send.send_hwm", ["must be >= 1", "got 0"]),
    ({"quantise": -1}, "send.quantise", ["must be >= 0", "got -1"]),
    ({"heartbeat_ttl_s": 7000}, "send.heartbeat_ttl_s", ["6553", "ZeroMQ"]),
    ({"endpoint": "http://x"}, "send.endpoint", ["ZeroMQ endpoint", "tcp://"]),
])
def test_send_errors_name_the_key_and_the_valid_values(send, path, must_say):
    e = _err({"send": send})
    assert e.path == path, str(e)
    assert str(e).startswith(path + ":")
    assert "expected SendConfig or null" not in str(e)
    for s in must_say:
        assert s in str(e), (s, str(e))


@pytest.mark.parametrize("extra,path,must_say", [
    ({"rnder": {}}, "rnder", ["unknown key 'rnder'", "did you mean 'render'", "send", "ring"]),
    ({"ring": {"points": 5}}, "ring.points", ["did you mean 'max_points'"]),   # a part of the name
    ({"render": {"camra": {}}}, "render.camra", ["did you mean 'camera'", "size", "backend"]),
    ({"render": {"camera": {"position": [1, "a", 2]}}}, "render.camera.position[1]", ["expected a number", "'a'"]),
    ({"render": {"camera": {"position": [1, 2]}}}, "render.camera.position", ["[x, y, z]"]),
    ({"render": {"cpu_crossover_points": -1}}, "render.cpu_crossover_points", [">= 0 or 'auto'"]),
    ({"policy": {"point_budget_cap": 0}}, "policy.point_budget_cap", ["must be >= 1"]),
    ({"render": {"size": [20000, 720]}}, "render.size", ["1..16384", "20000"]),
    ({"render": {"camera": {"fov_deg": 180}}}, "render.camera.fov_deg", ["(0, 180)"]),
    ({"ring": {"eviction": "random"}}, "ring.eviction", ["drop_oldest", "drop_newest", "importance"]),
])
def test_other_errors_name_the_key_and_the_valid_values(extra, path, must_say):
    e = _err(extra)
    assert e.path == path, str(e)
    for s in must_say:
        assert s in str(e), (s, str(e))


def test_an_unknown_key_with_nothing_close_lists_the_valid_keys_only():
    e = _err({"send": {"zzzz": 1}})
    assert e.path == "send.zzzz" and "did you mean" not in str(e) and "compression" in str(e)


def test_validate_prints_one_line_with_the_file_name(tmp_path, capsys):
    p = tmp_path / "sensor.yaml"
    p.write_text("source: {transport: synthetic}\nsend: {compresion: lz4}\n")
    assert main(["validate", str(p)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert str(p) in err and "send.compresion" in err and "did you mean 'compression'" in err


DOC_SAMPLES = {  # the bad.yaml behind each sample line of docs/config.md
    "ring.max_points": "source: {transport: synthetic}\nring: {max_points: 0}\n",
    "render.backend": "source: {transport: synthetic}\nrender: {backend: vulkan}\n",
    "send.compression": "source: {transport: synthetic}\nsend: {compression: gzip}\n",
    "rnder": "source: {transport: synthetic}\nrnder: {}\n",
}


def test_the_sample_errors_in_config_md_are_what_validate_prints(tmp_path, monkeypatch, capsys):
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[3] / "docs" / "config.md").read_text()
    shown = [l for l in doc.split("```")[1].splitlines() if l.startswith("config error:")]
    monkeypatch.chdir(tmp_path)
    printed = []
    for text in DOC_SAMPLES.values():
        Path("bad.yaml").write_text(text)
        assert main(["validate", "bad.yaml"]) == 1
        printed.append(capsys.readouterr().err.strip())
    assert printed == shown
