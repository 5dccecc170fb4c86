"""Bad input to each new call: a clear error naming the argument and what was expected;
counted; the pipeline and the other sources go on; nothing accepted is lost (issue 28, item 6)."""
from __future__ import annotations

import time

import numpy as np
import pytest

import pointflow
from pointflow import ConfigError, Pipeline, SendError
from pointflow.ingest.transports.api import check_transforms
from pointflow.show import _clouds

from .helpers import api_config

N = 100


@pytest.fixture(scope="module")
def pipe():
    p = Pipeline.from_dict(api_config(sources=[
        {"transport": "api", "name": "api"},
        {"transport": "synthetic", "name": "lidar", "options": {"scan_hz": 5, "points_per_scan": 500}}]), out_dir="")
    p.start()
    yield p
    p.stop()


def _good():
    return np.zeros((N, 3), np.float32) + np.arange(N, dtype=np.float32)[:, None], np.ones(N, np.float32)


BAD_SEND = [
    ("int_positions", lambda: (np.zeros((N, 3), np.int64), {}), "bad_dtype",
     ["positions", "float32 or float64", "int64"]),
    ("wrong_shape", lambda: (np.zeros((N, 2), np.float32), {}), "bad_shape", ["positions", "(n, 3)", f"({N}, 2)"]),
    ("not_numbers", lambda: ("abc", {}), "bad_dtype", ["positions", "float32 or float64"]),
    ("length_mismatch", lambda: (_good()[0], {"intensity": np.ones(N - 1, np.float32)}), "length_mismatch",
     ["channel 'intensity'", f"{N} points", f"({N - 1},)"]),
    ("channel_dtype", lambda: (_good()[0], {"intensity": np.ones(N, np.complex64)}), "bad_dtype",
     ["channel 'intensity'", "complex64", "float32"]),
    ("unknown_channel", lambda: (_good()[0], {"intensity": _good()[1], "intensty": _good()[1]}), "unknown_channel",
     ["channel 'intensty'", "intensity, rgb", "ring.extra_channels"]),
    # rgb the ring cannot hold: refused at send (it was accepted, then dropped or clipped by ingest)
    ("rgb_four_wide", lambda: (_good()[0], {"rgb": np.zeros((N, 4), np.uint8)}), "bad_channel_shape",
     ["channel 'rgb'", f"({N}, 3)", f"({N}, 4)"]),
    ("rgb_flat", lambda: (_good()[0], {"rgb": np.zeros(N, np.uint8)}), "bad_channel_shape",
     ["channel 'rgb'", f"({N}, 3)", f"({N},)"]),
    ("rgb_out_of_range", lambda: (_good()[0], {"rgb": np.tile(np.array([300, -5, 128], np.int32), (N, 1))}),
     "bad_value", ["channel 'rgb'", "0..255", "0..65535", "from -5 to 300"]),
]


@pytest.mark.parametrize("name,make,reason,words", BAD_SEND, ids=[b[0] for b in BAD_SEND])
def test_bad_send_is_refused_and_the_pipeline_goes_on(pipe, name, make, reason, words):
    before = pipe.stats()
    pos, chans = make()
    with pytest.raises(SendError) as ei:
        pipe.send(pos, **chans)
    msg = str(ei.value)
    assert ei.value.reason == reason and isinstance(ei.value, ValueError)
    for w in words:
        assert w in msg, msg
    assert "\n" not in msg
    _still_takes_clouds(pipe, before, rejected=reason)


@pytest.mark.parametrize("kw,words", [
    ({"frame": 7}, ["frame", "non-empty str", "7"]),
    ({"frame": ""}, ["frame", "non-empty str"]),
    ({"stamp_ns": -1}, ["stamp_ns", ">= 0", "-1"]),
    ({"stamp_ns": 1.5}, ["stamp_ns", "integer", "1.5"]),
], ids=["frame_int", "frame_empty", "stamp_negative", "stamp_float"])
def test_bad_frame_or_stamp(pipe, kw, words):
    before = pipe.stats()
    pos, inten = _good()
    with pytest.raises(SendError) as ei:
        pipe.send(pos, intensity=inten, **kw)
    for w in words:
        assert w in str(ei.value), str(ei.value)
    _still_takes_clouds(pipe, before, rejected=ei.value.reason)


def test_bad_source_name(pipe):
    with pytest.raises(ValueError, match=r"source: expected a source name \(a non-empty str\), got ''"):
        pipe.send(_good()[0], source="")
    with pytest.raises(ValueError, match="source 'lidar': 'lidar' is a source stage, not an api source"):
        pipe.send(_good()[0], source="lidar")
    with pytest.raises(ValueError, match="source 'ingest': 'ingest' is the ingest stage, not an api source"):
        pipe.send(_good()[0], source="ingest")  # it said "is a ingest stage"


@pytest.mark.parametrize("transforms,words", [
    ([{"parent": "map", "stamp_ns": 0, "translation": [0, 0, 0], "rotation": [0, 0, 0, 1]}],
     ["transforms[0]", "'parent' and 'child'"]),
    ([{"parent": "map", "child": "lidar", "stamp_ns": 0, "translation": [0, 0], "rotation": [0, 0, 0, 1]}],
     ["transforms[0].translation", "list of 3 numbers"]),
    ([{"parent": "map", "child": "lidar", "stamp_ns": -5, "translation": [0, 0, 0], "rotation": [0, 0, 0, 1]}],
     ["transforms[0].stamp_ns", ">= 0"]),
    ("map->lidar", ["transforms", "expected a list of transforms", "str"]),
], ids=["no_child", "short_translation", "negative_stamp", "not_a_list"])
def test_bad_transforms(pipe, transforms, words):
    before = pipe.stats()
    with pytest.raises(SendError) as ei:
        pipe.send_transforms(transforms)
    for w in words:
        assert w in str(ei.value), str(ei.value)
    _still_takes_clouds(pipe, before, rejected="bad_transform")


def test_transforms_accept_numpy_values():
    b = check_transforms({"parent": "map", "child": "lidar", "stamp_ns": np.int64(5),
                          "translation": np.array([1.0, 2.0, 3.0]), "rotation": (0, 0, 0, 1)})
    assert b.transforms[0].translation == (1.0, 2.0, 3.0) and b.transforms[0].stamp_ns == 5


def test_send_on_a_stopped_pipeline():
    p = Pipeline.from_dict(api_config(), out_dir="")
    with pytest.raises(RuntimeError, match="pipeline is not running: call start"):
        p.send(_good()[0])


def test_show_argument_errors():
    xyz = np.zeros((10, 3), np.float32)
    with pytest.raises(SendError, match=r"channel 'intensity': with a sequence of 2 clouds, expected a list of 2 arrays"):
        _clouds([xyz, xyz], {"intensity": np.ones(10, np.float32)})
    with pytest.raises(SendError, match=r"cloud 1: positions: expected shape \(n, 3\), got \(10, 2\)"):
        _clouds([xyz, xyz[:, :2]], {})
    with pytest.raises(SendError, match=r"color_by: 'speed' is not among the channels given \(intensity\)"):
        pointflow.show(xyz, color_by="speed", intensity=np.ones(10, np.float32))
    with pytest.raises(ValueError, match=r"view: expected one of (notebook, )?window, png, got 'holo'"):
        pointflow.show(xyz, view="holo")


def test_connect_option_errors_are_the_config_loaders(tmp_path):
    """Same loader, same messages as `pointflow send` (a send: section), before anything starts."""
    with pytest.raises(ConfigError, match=r"send\.endpoint: .*10\.1\.2\.3.*CURVE"):
        pointflow.connect("tcp://10.1.2.3:5556")
    with pytest.raises(ConfigError, match=r"send.curve_secret: unknown key 'curve_secret' \(did you mean 'curve_secret_key'\?\)"):
        pointflow.connect("tcp://127.0.0.1:5556", curve_secret="k")
    with pytest.raises(ConfigError, match=r"sources\[0\]\.options\.backpressure"):
        pointflow.connect("tcp://127.0.0.1:5556", backpressure="newest")


def _still_takes_clouds(pipe, before, rejected):
    """The refused call cost nothing: a good cloud afterwards is written, the synthetic source
    goes on, and the refusal is counted."""
    pos, inten = _good()
    assert pipe.send(pos, intensity=inten) == N
    want = before["stages"]["api"]["points_out"] + N
    end = time.monotonic() + 60
    while time.monotonic() < end:
        st = pipe.stats()
        if st["stages"]["api"]["points_out"] == want and st["accounting"]["ingest_received"] >= \
                before["accounting"]["ingest_received"] + N:
            break
        time.sleep(0.05)
    assert st["stages"]["api"]["points_out"] == want
    assert st["stages"]["api"]["rejected"].get(rejected, 0) == before["stages"]["api"]["rejected"].get(rejected, 0) + 1
    assert st["accounting"]["ingest_balanced"] and "failure" not in st
    assert st["stages"]["lidar"]["alive"] and st["stages"]["ingest"]["restarts"] == 0


# --------------------------------------------------------------- what a new user tried (issue 40)
def test_save_frame_writes_the_format_its_suffix_names(pipe, tmp_path):
    """``.jpg``/``.jpeg`` hold JPEG bytes, ``.png`` PNG; another suffix is refused before the
    render stage is asked, naming the suffixes, and the next save works."""
    from PIL import Image

    for name, magic, fmt in (("f.jpg", b"\xff\xd8\xff", "JPEG"), ("f.JPEG", b"\xff\xd8\xff", "JPEG"),
                             ("f.png", b"\x89PNG\r\n\x1a\n", "PNG")):
        out = pipe.save_frame(str(tmp_path / name))
        assert open(out, "rb").read(len(magic)) == magic, name
        with Image.open(out) as img:
            assert img.format == fmt and img.size == (64, 48)
    for name in ("f.bmp", "frame"):
        with pytest.raises(ValueError) as ei:
            pipe.save_frame(str(tmp_path / name))
        msg = str(ei.value)
        assert "save_frame" in msg and name in msg and ".png, .jpg, .jpeg" in msg and "\n" not in msg, msg
        assert not (tmp_path / name).exists()
    assert open(pipe.save_frame(str(tmp_path / "after.png")), "rb").read(4) == b"\x89PNG"
    # under a plain file: refused here, naming it (the render stage raised FileExistsError)
    (tmp_path / "afile").write_text("x")
    with pytest.raises(ValueError, match=f"path: {tmp_path / 'afile'} is a file, not a folder"):
        pipe.save_frame(str(tmp_path / "afile" / "sub" / "f.png"))
    assert open(pipe.save_frame(str(tmp_path / "new" / "dir" / "f.png")), "rb").read(4) == b"\x89PNG"


def test_show_outside_a_notebook_says_so(pipe, capsys):
    """``p.show()`` in a script has no notebook to show a widget in: it says so, and what works
    there, on one line of stderr, instead of returning a widget nobody sees."""
    assert pipe.show() is None
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "not inside a Jupyter notebook" in err, err
    for way in ("render.window: true", "--serve", "save_frame"):
        assert way in err, err


def test_a_kernel_shell_subclass_counts_as_a_notebook(monkeypatch):
    """``p.show()`` and ``pointflow.show`` take a kernel's shell for a notebook also when it
    subclasses ZMQInteractiveShell (Google Colab's does); a terminal IPython is not one."""
    import sys
    import types

    from pointflow.show import in_notebook

    ZMQInteractiveShell = type("ZMQInteractiveShell", (), {})
    shells = {"kernel": type("Shell", (ZMQInteractiveShell,), {})(),
              "terminal": type("TerminalInteractiveShell", (), {})()}
    for name, want in (("kernel", True), ("terminal", False)):
        fake = types.SimpleNamespace(get_ipython=lambda s=shells[name]: s)
        monkeypatch.setitem(sys.modules, "IPython", fake)
        assert in_notebook() is want, name
