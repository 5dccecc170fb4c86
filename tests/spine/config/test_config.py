"""Config errors name the key path and what was expected, before anything starts."""
import textwrap

import pytest

from pointflow.config import ConfigError, load_config

BASE = {"source": {"transport": "synthetic"}}


def _err(data) -> ConfigError:
    with pytest.raises(ConfigError) as ei:
        load_config(data)
    return ei.value


def with_(path: str, value):
    d = {"source": {"transport": "synthetic"}}
    keys = path.split(".")
    cur = d
    for k in keys[:-1]:
        cur = cur.setdefault(k, {})
    cur[keys[-1]] = value
    return d


def test_demo_config_loads():
    cfg = load_config("configs/demo.yaml")
    assert cfg.sources[0].transport == "synthetic"
    assert cfg.ring.max_points == 1_000_000
    assert cfg.render.color_by == "intensity"
    assert cfg.ring_channels() == ["intensity"]


@pytest.mark.parametrize("path,value,fragment", [
    ("ring.max_points", 0, "must be >= 1"),
    ("ring.max_points", -5, "must be >= 1"),
    ("ring.max_points", "lots", "expected an integer"),
    ("ring.max_points", 1.5, "expected an integer"),
    # YAML reads 1.5e6 as text: the message says how to write it (1.5e+6, a float, is taken)
    ("ring.max_points", "1.5e6", "(YAML reads 1.5e6 as text; write 1500000)"),
    ("cadence.target_hz", "1e1", "(YAML reads 1e1 as text; write 10)"),
    ("ring.eviction", "random", "must be one of drop_oldest, drop_newest, importance"),
    ("cadence.target_hz", -60, "must be > 0"),
    ("cadence.target_hz", 0, "must be > 0"),
    ("cadence.target_hz", float("nan"), "must be finite"),
    ("render.backend", "vulkan", "must be one of auto, wgpu, gl, cpu"),
    ("render.size", [0, 720], "render.size"),
    ("render.size", [1280], "render.size"),
    ("render.size", "big", "expected a list"),
    ("render.point_size", 0, "must be > 0"),
    ("render.output.every_n_frames", 0, "must be >= 1"),
    ("render.camera.near", 20000.0, "less than camera.far"),
    ("render.adaptive", True, "unknown key"),
    ("ingest.coalesce_points", True, "expected an integer"),
    ("endpoints.ingest", "http://x", "ZeroMQ endpoint"),
    ("supervisor.max_restarts", -1, "must be >= 0"),
])
def test_bad_values_name_the_key(path, value, fragment):
    e = _err(with_(path, value))
    expected_path = path if fragment != "unknown key" else path
    assert e.path.startswith(expected_path.split(".")[0])
    assert expected_path in str(e) or e.path == expected_path
    assert fragment in str(e)


def test_unknown_top_level_key():
    e = _err({**BASE, "rnder": {}})
    assert e.path == "rnder" and "unknown key" in str(e) and "render" in str(e)


def test_unknown_transport_is_named():
    e = _err({"source": {"transport": "carrier-pigeon"}})
    assert e.path == "sources[0].transport"
    assert "carrier-pigeon" in str(e) and "synthetic" in str(e)


def test_missing_source():
    e = _err({"ring": {"max_points": 10}})
    assert e.path == "sources"


def test_duplicate_source_names():
    e = _err({"sources": [{"transport": "synthetic", "name": "a"}, {"transport": "synthetic", "name": "a"}]})
    assert e.path == "sources[1].name"


def test_transport_options_validated_at_load():
    e = _err({"source": {"transport": "synthetic", "options": {"no_such_option": 1}}})
    assert e.path == "sources[0].options.no_such_option"


def test_yaml_file_errors(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("source: [unclosed\n")
    e = _err(str(p))
    assert "invalid YAML" in str(e)
    e = _err(str(tmp_path / "missing.yaml"))
    assert "cannot read" in str(e)


def test_yaml_roundtrip(tmp_path):
    p = tmp_path / "ok.yaml"
    p.write_text(textwrap.dedent("""
        sources:
          - {transport: synthetic, name: lidar}
        ring: {max_points: 5000, eviction: importance}
        render: {size: [320, 240], color_range: [0, 1]}
    """))
    cfg = load_config(str(p))
    assert cfg.sources[0].name == "lidar"
    assert cfg.ring.importance_field == "auto"  # importance eviction needs a field
    assert cfg.render.color_range == [0.0, 1.0]
    assert cfg.base_dir == str(tmp_path)


def test_cli_validate_reports_key(tmp_path, capsys):
    from pointflow.cli import main

    p = tmp_path / "c.yaml"
    p.write_text("source: {transport: synthetic}\nring: {max_points: 0}\n")
    assert main(["validate", str(p)]) == 1
    err = capsys.readouterr().err
    assert "ring.max_points" in err and "must be >= 1" in err


def test_checked_in_json_schema_is_current_and_validates_configs():
    import json
    from pathlib import Path

    import jsonschema
    import yaml

    from pointflow.config import json_schema

    root = Path(__file__).resolve().parents[3]
    schema = json.loads((root / "pointflow.schema.json").read_text())
    assert schema == json.loads(json.dumps(json_schema())), "regenerate: pointflow schema > pointflow.schema.json"
    for path in sorted((root / "configs").glob("*.yaml")):
        jsonschema.validate(yaml.safe_load(path.read_text()), schema)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({"source": {"transport": "synthetic"}, "ring": {"max_points": "many"}}, schema)


def test_a_section_with_a_switch_takes_true_or_false():
    """``render.edl: true`` (as the README says it) stands for ``{enabled: true}``, and so does
    any section with an ``enabled`` switch (``tracing: false``); the schema says so; other
    values still name the key."""
    import jsonschema

    from pointflow.config import json_schema

    cfg = load_config({**BASE, "render": {"edl": True}, "tracing": False})
    assert cfg.render.edl.enabled is True and cfg.render.edl.strength == 1.0 and cfg.tracing.enabled is False
    assert load_config({**BASE, "render": {"edl": False}}).render.edl.enabled is False
    e = _err({**BASE, "render": {"edl": "yes"}})
    assert e.key == "render.edl" and "expected a mapping" in str(e)
    jsonschema.validate({**BASE, "render": {"edl": True}, "tracing": False}, json_schema())
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({**BASE, "render": {"edl": "yes"}}, json_schema())


def test_a_whole_float_is_an_integer():
    """YAML's 1.5e+6 is a float: a whole one is taken where an integer is expected."""
    assert load_config(with_("ring.max_points", 1.5e6)).ring.max_points == 1_500_000
