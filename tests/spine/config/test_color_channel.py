"""``render.color_by`` naming a channel no source has (issue 31.7): refused at load where the
sources declare their channels (synthetic, file), else one warning from ingest naming the
channels that do arrive, and the points drawn in the documented fallback ``render.color`` (they
were drawn dark red: a never-written channel read as 0)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pointflow.config import ConfigError, load_config
from pointflow import formats

from ..helpers import small_config

REPO = Path(__file__).resolve().parents[3]


def _refused(cfg: dict, base_dir: str = ".") -> str:
    with pytest.raises(ConfigError) as e:
        load_config(cfg, base_dir=base_dir)
    assert e.value.path == "render.color_by", str(e.value)
    return str(e.value)


def test_a_misspelt_channel_of_a_synthetic_source_is_refused_at_load():
    msg = _refused(small_config(render={"color_by": "hieght"}))
    assert "no source has a channel 'hieght'" in msg and "did you mean 'height'" in msg, msg
    assert "classification, intensity" in msg, msg  # the channels the source has
    # what the source declares is what counts: beam is a synthetic channel, if asked for
    _refused(small_config(render={"color_by": "beam"}))
    cfg = small_config(render={"color_by": "beam"})
    cfg["source"]["options"]["channels"] = ["intensity", "beam"]
    load_config(cfg)
    for ok in ("z", "height", "ingest_time", "none", None, "intensity", "classification"):
        load_config(small_config(render={"color_by": ok}))


def test_file_sources_declare_their_channels(tmp_path):
    pos = np.random.default_rng(0).normal(size=(50, 3))
    formats.write_ply(str(tmp_path / "a.ply"), pos, {"reflectivity": np.ones(50, np.float32)})
    src = {"transport": "file", "options": {"path": "a.ply"}}
    msg = _refused({"source": src, "render": {"color_by": "range"}}, str(tmp_path))
    assert "the sources' channels: reflectivity" in msg, msg
    load_config({"source": src, "render": {"color_by": "reflectivity"}}, base_dir=str(tmp_path))
    src["options"]["rename"] = {"reflectivity": "range"}  # renamed as the points will be sent
    load_config({"source": src, "render": {"color_by": "range"}}, base_dir=str(tmp_path))
    # an xyz-only file with the default colour (intensity) is not an error: drawn in render.color
    np.save(tmp_path / "xyz.npy", pos)
    load_config({"source": {"transport": "file", "options": {"path": "xyz.npy"}}}, base_dir=str(tmp_path))


def test_a_las_file_declares_its_dimensions(tmp_path):
    laspy = pytest.importorskip("laspy")
    las = laspy.create(point_format=0, file_version="1.2")
    las.x, las.y, las.z = np.arange(5.0), np.arange(5.0), np.arange(5.0)
    las.write(str(tmp_path / "a.las"))
    src = {"transport": "file", "options": {"path": "a.las"}}
    msg = _refused({"source": src, "render": {"color_by": "gps_time"}}, str(tmp_path))  # format 0 has none
    assert "classification, intensity, return_number" in msg, msg
    load_config({"source": src, "render": {"color_by": "classification"}}, base_dir=str(tmp_path))


def test_validate_refuses_it_in_one_line(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("source: {transport: synthetic}\nrender: {color_by: hieght}\n")
    r = subprocess.run([sys.executable, "-m", "pointflow.cli", "validate", str(path)], capture_output=True,
                       text=True, timeout=60, env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert r.returncode == 1 and r.stdout == "", (r.returncode, r.stdout, r.stderr)
    assert r.stderr.count("\n") == 1 and "render.color_by: no source has a channel 'hieght'" in r.stderr, r.stderr


PLUGIN = '''
import numpy as np
from pointflow.chunk import PointChunk
from pointflow.ingest.transports.base import Transport


class Blob(Transport):
    """Channels known only when the points arrive (declares none)."""
    name = "blob"
    lossless = True

    def chunks(self):
        rng = np.random.default_rng(1)
        for _ in range(20):
            yield PointChunk(positions=rng.normal(size=(2000, 3)),
                             channels={"intensity": rng.random(2000).astype(np.float32)}, source_id=self.source_id)
'''


@pytest.mark.timeout(180)
def test_an_undeclared_source_gets_one_warning_and_the_fallback_colour(tmp_path):
    from PIL import Image

    (tmp_path / "blob31_plugin.py").write_text(PLUGIN)
    cfg = small_config(source={"transport": "blob31_plugin:Blob"},
                       render={"backend": "cpu", "size": [96, 64], "color_by": "hieght", "color": [0.0, 1.0, 0.0],
                               "background": [0.0, 0.0, 0.0], "output": {"dir": str(tmp_path / "out"),
                                                                          "every_n_frames": 1}})
    path = tmp_path / "c.yaml"
    path.write_text(json.dumps(cfg))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), str(tmp_path)]))
    r = subprocess.run([sys.executable, "-m", "pointflow.cli", "run", str(path), "--duration", "6", "-q"],
                       capture_output=True, text=True, timeout=150, env=env, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    warn = [ln for ln in r.stderr.splitlines() if "hieght" in ln and " INFO " not in ln]
    assert len(warn) == 1, "\n".join(warn)
    assert " WARNING " in warn[0] and "channels that arrive: intensity" in warn[0] and "render.color" in warn[0], warn
    img = np.asarray(Image.open(tmp_path / "out" / "last.png"))[..., :3].reshape(-1, 3)
    drawn = img[(img != 0).any(axis=1)]
    assert drawn.shape[0] > 0, "nothing drawn"
    assert (drawn == [0, 255, 0]).all(), np.unique(drawn, axis=0)[:5]  # render.color, not the colormap
