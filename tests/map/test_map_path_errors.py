"""A ``map:`` path that cannot be a map (issue 37): not a point file, missing, a directory, empty,
a point file's extension on something else, unreadable. ``pointflow validate``, ``run`` and
``profile`` each print one line naming ``map.path`` and exit with the config-error code before
anything starts. A file that passes those checks and is broken further in (a LAZ cut short)
is the map stage's error at run time: the live part is drawn, and the run exits 2, never 0."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from pointflow.cli import EXIT_CONFIG, main

from .mapfiles import write_las

COMMANDS = [["validate"], ["run", "--duration", "1", "-q"], ["profile", "--duration", "1", "-q"]]
README = os.path.join(os.path.dirname(__file__), "..", "..", "README.md")


def _bad(tmp_path, kind: str) -> str:
    if kind == "readme":
        return os.path.abspath(README)
    p = tmp_path / {"missing": "nope.laz", "directory": "adir.las", "empty": "empty.laz", "text_as_laz": "fake.laz",
                    "text_as_ply": "fake.ply", "text_as_pcd": "fake.pcd", "unreadable": "locked.las",
                    "garbage_header": "garbage.las", "cut_laz": "cut.laz"}[kind]
    if kind == "cut_laz":  # cut short after its header: the chunk table it points to is not there
        whole = write_las(str(tmp_path / "whole.laz"), 20_000)
        p.write_bytes(open(whole, "rb").read()[:2000])
        return str(p)
    if kind == "garbage_header":  # the signature, then noise: its header promises ~3.5e9 VLRs (laspy
        import numpy as np       # looped on them for minutes and the run hung, exiting 0)

        p.write_bytes(b"LASF" + np.random.default_rng(3).integers(0, 256, 5000, dtype=np.uint8).tobytes())
        return str(p)
    if kind == "directory":
        p.mkdir()
    elif kind == "empty":
        p.write_bytes(b"")
    elif kind.startswith("text_as"):
        p.write_text("# a README, not points\nhello\n")
    elif kind == "unreadable":
        write_las(str(p), 100)
        p.chmod(0)
    return str(p)


@pytest.mark.parametrize("cmd", COMMANDS, ids=lambda c: c[0])
@pytest.mark.parametrize("kind", ["readme", "missing", "directory", "empty", "text_as_laz", "text_as_ply",
                                  "text_as_pcd", "unreadable", "garbage_header", "cut_laz"])
def test_a_map_path_that_is_not_a_point_file_is_one_line_naming_it(tmp_path, capsys, cmd, kind):
    path = _bad(tmp_path, kind)
    if kind == "unreadable" and os.access(path, os.R_OK):
        pytest.skip("running as root: a mode-0 file is still readable")
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"source: {{transport: synthetic}}\nmap: {{path: {path}}}\n")
    code = main([cmd[0], str(cfg), *cmd[1:], *(["--out", str(tmp_path / "out")] if cmd[0] != "validate" else [])])
    err = capsys.readouterr().err
    assert code == EXIT_CONFIG, err
    assert "Traceback" not in err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("config error: ") and "map.path: " in lines[0], err
    assert path in lines[0]
    assert not (tmp_path / "out").exists(), "nothing started"


def test_a_broken_map_file_fails_the_run_with_exit_2(tmp_path):
    """A LAZ whose compressed points are noise in the middle: its header and chunk table pass
    the load checks; the run draws the live part and ends with the map stage's one line and
    exit status 2. (A LAZ cut short is refused at load: its chunk table is past its end.)"""
    whole = write_las(str(tmp_path / "whole.laz"), 20_000)
    cut = tmp_path / "cut.laz"
    raw = bytearray(open(whole, "rb").read())
    mid = len(raw) // 3
    raw[mid:mid + 4000] = bytes(range(256)) * 15 + bytes(160)
    cut.write_bytes(bytes(raw))
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"source: {{transport: synthetic, options: {{points_per_scan: 2000}}}}\n"
                   f"map: {{path: {cut}, cache_dir: {tmp_path / 'cache'}}}\n"
                   f"render: {{backend: cpu, size: [64, 48]}}\n")
    assert main(["validate", str(cfg)]) == 0
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([os.getcwd(), os.environ.get("PYTHONPATH", "")]))
    r = subprocess.run([sys.executable, "-m", "pointflow.cli", "run", str(cfg), "--duration", "6", "-q",
                        "--out", str(tmp_path / "out")], capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 2, (r.returncode, r.stderr[-3000:])
    assert "Traceback" not in r.stderr
    last = [ln for ln in r.stderr.splitlines() if ln.strip()][-1]
    assert last.startswith("error: map not shown: ") and str(cut) in last, r.stderr[-3000:]


@pytest.mark.parametrize("kind", ["under_proc", "under_a_file", "a_file", "relative"])
def test_map_cache_dir_is_checked_at_load_and_relative_to_the_config(tmp_path, capsys, kind):
    """map.cache_dir is made at load, resolved against the config's folder as map.path is; one
    that cannot be is one line naming the key (it was a raw OSError when the map opened)."""
    las = write_las(str(tmp_path / "t.las"), 100)
    (tmp_path / "afile").write_text("x")
    d = {"under_proc": "/proc/pf_cache_test", "under_a_file": str(tmp_path / "afile" / "sub"),
         "a_file": str(tmp_path / "afile"), "relative": "rel_cache"}[kind]
    sub = tmp_path / "cfg"
    sub.mkdir()
    cfg = sub / "c.yaml"
    cfg.write_text(f"source: {{transport: synthetic}}\nmap: {{path: {las}, cache_dir: {d}}}\n")
    code = main(["validate", str(cfg)])
    err = capsys.readouterr().err
    if kind == "relative":
        assert code == 0, err
        assert (sub / "rel_cache").is_dir(), "relative to the config's folder, not the working directory"
        return
    assert code == EXIT_CONFIG and "Traceback" not in err, err
    lines = err.splitlines()
    assert len(lines) == 1 and "map.cache_dir: " in lines[0], err


def test_a_map_on_its_own_is_a_config(tmp_path):
    """A config with a map: block and no source (README: a big file goes in a map: block) was
    refused ('sources: required key is missing'); it gets an idle api source."""
    from pointflow.config import load_config

    las = write_las(str(tmp_path / "t.las"), 100)
    cfg = tmp_path / "m.yaml"
    cfg.write_text(f"map: {{path: {las}}}\n")
    c = load_config(str(cfg))
    assert [(s.name, s.transport) for s in c.sources] == [("api", "api")]
    assert main(["validate", str(cfg)]) == 0
