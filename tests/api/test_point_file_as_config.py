"""A point file handed to ``pointflow run``/``validate`` where a pipeline YAML belongs (issue 40):
one line that says it is a point file and how to show it, not "not UTF-8, save the file as
UTF-8"; the config the line suggests loads."""
from __future__ import annotations

import re

import numpy as np
import pytest

from pointflow.cli import main
from pointflow.config import load_config


def _las_header(path, size: int = 0):
    with open(path, "wb") as f:
        f.write(b"LASF" + bytes(range(1, 200)))
        if size:
            f.truncate(size)  # sparse: a big file on disk costs nothing


@pytest.mark.parametrize("name,size,kind", [
    ("scan.las", 0, "LAS"), ("tile.copc.laz", 0, "COPC"),
    ("big.las", 40 << 20, "LAS"),   # over the config size limit: still named a point file
    ("renamed.dat", 0, "LAS/LAZ"),  # by its first bytes
], ids=["las", "copc", "bigger_than_a_config", "by_magic"])
@pytest.mark.parametrize("cmd", ["run", "validate"])
def test_a_point_file_given_as_the_config(tmp_path, capsys, cmd, name, size, kind):
    path = tmp_path / name
    _las_header(path, size)
    assert main([cmd, str(path)]) == 1
    cap = capsys.readouterr()
    err = cap.err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err, err
    assert f"a {kind} point file, not a pipeline config" in err and str(path) in err, err
    assert "UTF-8" not in err and "bytes is not a pipeline config" not in err, err
    assert f"source: {{transport: file, options: {{path: {name}}}}}" in err, err
    assert f"`map: {{path: {name}}}`" in err and "docs/map.md" in err, err


def test_the_suggested_config_loads(tmp_path, capsys):
    """Saved beside the point file as the line says, the suggested YAML is a valid pipeline."""
    np.save(tmp_path / "cloud.npy", np.random.default_rng(0).normal(size=(100, 3)))
    assert main(["run", str(tmp_path / "cloud.npy")]) == 1
    err = capsys.readouterr().err
    assert "a NPY point file" in err and "map:" not in err, err  # the map layer does not read .npy
    snippet = re.search(r"`(source: \{transport: file.*?\}\})`", err).group(1)
    (tmp_path / "cloud.yaml").write_text(snippet + "\n")
    cfg = load_config(tmp_path / "cloud.yaml")
    assert cfg.sources[0].transport == "file"
    assert main(["validate", str(tmp_path / "cloud.yaml")]) == 0


def test_a_config_that_is_not_utf8_still_says_so(tmp_path, capsys):
    path = tmp_path / "pipe.yaml"
    path.write_bytes(b"name: caf\xe9\n")
    assert main(["validate", str(path)]) == 1
    assert "not UTF-8 text" in capsys.readouterr().err
