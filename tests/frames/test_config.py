"""The frames block is validated at load; errors name the key."""
import pytest

from pointflow.config import ConfigError, json_schema, load_config


def _load(frames, **src):
    return load_config({"source": {"transport": "synthetic", **src}, "frames": frames})


def test_issue_block_loads_and_defaults_mean_as_sent():
    cfg = _load({"fixed": "odom", "tf_wait_ms": 200, "deskew": "auto", "static": [
        {"parent": "base_link", "child": "lidar_top", "translation": [0.9, 0, 1.7], "rpy_deg": [0, 2, 0]},
        {"parent": "base_link", "child": "lidar_left", "translation": [0.3, 0.8, 1.2],
         "quaternion": [0, 0, 0.7071068, 0.7071068]}]}, frame_id="lidar_top")
    assert cfg.frames.fixed == "odom" and cfg.sources[0].frame_id == "lidar_top"
    assert load_config({"source": {"transport": "synthetic"}}).frames.fixed is None
    assert "frames" in json_schema()["properties"]


@pytest.mark.parametrize("frames,key,text", [
    ({"static": [{"parent": "a", "child": "b"}, {"parent": "a", "child": "c", "quaternion": [0, 0, 1, 1]}]},
     "frames.static[1].quaternion", "unit quaternion"),
    ({"static": [{"parent": "a", "child": "b", "rpy_deg": [0, 0, 1], "quaternion": [0, 0, 0, 1]}]},
     "frames.static[0].quaternion", "not both"),
    ({"static": [{"parent": "a", "child": "b"}, {"parent": "c", "child": "b"}]}, "frames.static[1]", "already has parent"),
    ({"static": [{"parent": "a", "child": "b"}, {"parent": "b", "child": "a"}]}, "frames.static[1]", "loop"),
    ({"static": [{"parent": "a", "child": "b", "translation": [1, 2]}]}, "frames.static[0].translation", "[x, y, z]"),
    ({"deskew": {"field": "t", "unit": "ms"}}, "frames.deskew.unit", "ns, us, s"),
    ({"deskew": "sometimes"}, "frames.deskew", "auto"),
    ({"tf_wait_ms": -1}, "frames.tf_wait_ms", ">= 0"),
    ({"fixed": " "}, "frames.fixed", "frame name"),
    ({"fixd": "odom"}, "frames.fixd", "unknown key"),
])
def test_errors_name_the_key(frames, key, text):
    with pytest.raises(ConfigError) as e:
        _load(frames)
    assert e.value.path == key and text in str(e.value), str(e.value)


def test_source_frame_id_must_be_a_name():
    with pytest.raises(ConfigError) as e:
        _load({}, frame_id="")
    assert e.value.path == "sources[0].frame_id"
