"""The level-of-detail index: every node is exactly the file's points, built once, rebuilt on change."""
from __future__ import annotations

import json
import logging
import os

import numpy as np
import pytest

from pointflow.map import build, inputs, open_map

from .mapfiles import all_nodes, laspy_points, write_las, write_pcd, write_ply


def check_exact(source, path):
    """Union of all nodes == laspy's read of the file (every channel), no point twice, each
    point inside its node's cube."""
    got, loads = all_nodes(source)
    want = laspy_points(path)
    assert got["positions"].shape == want["positions"].shape
    assert np.array_equal(got["gps_time"], np.arange(want["gps_time"].shape[0], dtype=np.float64)), "duplicates or losses"
    for name in want:
        assert np.array_equal(got[name], want[name]), name
        assert got[name].dtype == want[name].dtype or name == "rgb", (name, got[name].dtype, want[name].dtype)
    for key, d in loads:
        n = source.node(key)
        assert d["positions"].shape[0] == n.count > 0
        assert np.all(d["positions"] >= n.lo - 1e-6) and np.all(d["positions"] <= n.hi + 1e-6), key


@pytest.mark.parametrize("ext", ["las", "laz"])
def test_every_node_is_exactly_the_files_points(tmp_path, ext):
    path = write_las(str(tmp_path / f"t.{ext}"), 60_000, seed=1)
    with open_map(path, cache_dir=str(tmp_path / "cache"), progress=False) as m:
        assert m.point_count == 60_000
        assert {"intensity", "classification", "gps_time", "rgb"} <= set(m.channels)
        check_exact(m, path)
        depths = {k[1] for k in m.keys()}
        assert max(depths) >= 1 and len(m.keys()) > 2  # 60 k points > one leaf: a real tree


def test_many_cells_and_splits_stay_exact(tmp_path, monkeypatch):
    """The big-file path (spill files per cell, a cell split again) on a small file."""
    monkeypatch.setattr(build, "CELL_TARGET", 2_000)
    monkeypatch.setattr(build, "MAX_CELL", 6_000)
    monkeypatch.setattr(build, "CHUNK_POINTS", 7_000)
    monkeypatch.setattr(inputs, "CHUNK_POINTS", 7_000)
    path = write_las(str(tmp_path / "t.laz"), 50_000, seed=2)
    with open_map(path, cache_dir=str(tmp_path / "cache"), progress=False) as m:
        check_exact(m, path)
        meta = json.load(open(os.path.join(m.files[0].dir, "meta.json")))
        assert meta["count"] == 50_000


def test_inner_nodes_are_a_spread_out_subset(tmp_path):
    path = write_las(str(tmp_path / "t.laz"), 80_000, seed=3)
    with open_map(path, cache_dir=str(tmp_path / "cache"), progress=False) as m:
        root = m.root_keys()[0]
        pts = m.load(root)["positions"]
        assert 0 < pts.shape[0] < 80_000 // 2
        lo, hi = m.bounds
        span = (pts.max(axis=0) - pts.min(axis=0))[:2] / (hi - lo)[:2]
        assert np.all(span > 0.95), span  # the root covers the whole map, not a corner
        # one point per cell of the root's 128^3 grid
        f = m.files[0]
        cells = np.floor((pts - f.cube_lo) / f.cube_side * 128).astype(np.int64)
        assert np.unique(cells, axis=0).shape[0] == pts.shape[0]
        # children of an inner node exist and each child key is inside its parent
        kids = m.children(root)
        assert kids and all(k[1] == 1 for k in kids)


def test_index_is_built_once_and_rebuilt_when_the_file_changes(tmp_path, caplog):
    path = write_las(str(tmp_path / "t.laz"), 30_000, seed=4)
    cache = str(tmp_path / "cache")
    calls = []
    open_map(path, cache_dir=cache, progress=lambda d, t: calls.append((d, t))).close()
    assert calls and calls[-1] == (30_000, 30_000)
    calls.clear()
    with open_map(path, cache_dir=cache, progress=lambda d, t: calls.append((d, t))) as m:
        assert not calls  # reused
        assert len(os.listdir(cache)) == 1
    write_las(path, 31_000, seed=5)  # a changed file
    with caplog.at_level(logging.WARNING, logger="pointflow.map.lod"):
        with open_map(path, cache_dir=cache, progress=lambda d, t: calls.append((d, t))) as m:
            assert m.point_count == 31_000 and calls
            check_exact(m, path)
    assert any("changed" in r.getMessage() and path in r.getMessage() for r in caplog.records)
    assert len(os.listdir(cache)) == 1  # replaced, no leftovers


def test_index_of_another_version_is_rebuilt_with_a_warning(tmp_path, caplog):
    path = write_las(str(tmp_path / "t.las"), 5_000, seed=6)
    cache = str(tmp_path / "cache")
    with open_map(path, cache_dir=cache, progress=False) as m:
        meta_path = os.path.join(m.files[0].dir, "meta.json")
    meta = json.load(open(meta_path))
    meta["version"] = build.INDEX_VERSION + 99
    json.dump(meta, open(meta_path, "w"))
    with caplog.at_level(logging.WARNING, logger="pointflow.map.lod"):
        with open_map(path, cache_dir=cache, progress=False) as m:
            check_exact(m, path)
    msgs = [r.getMessage() for r in caplog.records]
    assert any("version" in s and path in s for s in msgs), msgs
    assert json.load(open(meta_path))["version"] == build.INDEX_VERSION


def test_damaged_index_is_rebuilt(tmp_path, caplog):
    path = write_las(str(tmp_path / "t.las"), 5_000, seed=7)
    cache = str(tmp_path / "cache")
    with open_map(path, cache_dir=cache, progress=False) as m:
        pts = os.path.join(m.files[0].dir, "points.bin")
    with open(pts, "r+b") as f:
        f.truncate(1000)
    with caplog.at_level(logging.WARNING, logger="pointflow.map.lod"):
        with open_map(path, cache_dir=cache, progress=False) as m:
            check_exact(m, path)
    assert any("points.bin" in r.getMessage() for r in caplog.records)


def test_ply_written_by_plyfile(tmp_path):
    path = str(tmp_path / "t.ply")
    pos, ch = write_ply(path, 30_000, seed=8)
    with open_map(path, cache_dir=str(tmp_path / "cache"), progress=False) as m:
        assert m.point_count == 30_000 and set(m.channels) >= {"rgb", "intensity"}
        got, _ = all_nodes(m)
    order_got = np.lexsort(got["positions"].T[::-1])
    order_want = np.lexsort(pos.T[::-1])
    assert np.array_equal(got["positions"][order_got], pos[order_want])
    assert np.array_equal(got["rgb"][order_got], ch["rgb"][order_want])
    assert np.array_equal(got["intensity"][order_got], ch["intensity"][order_want])


def test_pcd(tmp_path):
    path = str(tmp_path / "t.pcd")
    pos, ch = write_pcd(path, 25_000, seed=9)
    with open_map(path, cache_dir=str(tmp_path / "cache"), progress=False) as m:
        got, _ = all_nodes(m)
    og, ow = np.lexsort(got["positions"].T[::-1]), np.lexsort(pos.T[::-1])
    assert np.array_equal(got["positions"][og], pos[ow].astype(np.float64))
    assert np.array_equal(got["intensity"][og], ch["intensity"][ow])


def test_progress_line_on_stderr(tmp_path, capfd):
    path = write_las(str(tmp_path / "t.laz"), 20_000, seed=10)
    open_map(path, cache_dir=str(tmp_path / "cache")).close()
    err = capfd.readouterr().err
    assert "map: indexing t.laz" in err and "100%" in err and "points/s" in err


def test_default_cache_dir_follows_xdg(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    path = write_las(str(tmp_path / "t.las"), 2_000, seed=11)
    with open_map(path, progress=False) as m:
        assert m.files[0].dir.startswith(str(tmp_path / "xdg" / "pointflow" / "map"))


def test_empty_and_tiny_files(tmp_path):
    path = write_las(str(tmp_path / "one.las"), 1, seed=12)
    with open_map(path, cache_dir=str(tmp_path / "c"), progress=False) as m:
        assert m.point_count == 1 and len(m.keys()) == 1
        check_exact(m, path)


def test_two_files_one_map(tmp_path):
    a = write_las(str(tmp_path / "a.laz"), 10_000, seed=13)
    b = write_las(str(tmp_path / "b.las"), 12_000, seed=14)
    with open_map([a, b], cache_dir=str(tmp_path / "c"), progress=False) as m:
        assert m.point_count == 22_000 and len(m.root_keys()) == 2
        assert {m.source_name(k) for k in m.root_keys()} == {"a.laz", "b.las"}
        assert sum(m.node(k).count for k in m.keys()) == 22_000


def test_morton_codes_give_each_depths_cell():
    from pointflow.map import kernels

    rng = np.random.default_rng(5)
    lo, side = np.array([10.0, -5.0, 100.0]), 64.0
    pos = lo + rng.uniform(0, side, (5000, 3))
    codes = kernels.morton_codes(pos, lo, side)
    for d in (0, 1, 3, 7, 21):
        xyz = kernels.decode_prefixes(codes >> np.uint64(3 * (kernels.DMAX - d)))
        want = np.floor((pos - lo) / side * (1 << d)).astype(np.int64)
        assert np.array_equal(xyz, np.minimum(want, (1 << d) - 1)), d


def test_loads_from_many_threads_agree(tmp_path):
    from concurrent.futures import ThreadPoolExecutor

    path = write_las(str(tmp_path / "t.laz"), 60_000, seed=15)
    with open_map(path, cache_dir=str(tmp_path / "cache"), progress=False) as m:
        keys = m.keys() * 4
        with ThreadPoolExecutor(4) as ex:
            got = list(ex.map(m.load, keys))
        for k, d in zip(keys, got):
            assert np.array_equal(d["gps_time"], m.load(k)["gps_time"])


def test_header_bounds_that_do_not_hold_the_points(tmp_path, caplog):
    """A writer that left the header's bounds at zero: indexed again with the points' own
    bounds (a warning), and still exactly the file's points."""
    import struct

    path = write_las(str(tmp_path / "t.las"), 30_000, seed=16)
    with open(path, "r+b") as f:
        f.seek(179)
        f.write(struct.pack("<6d", 0, 0, 0, 0, 0, 0))  # max x, min x, max y, min y, max z, min z
    with caplog.at_level(logging.WARNING, logger="pointflow.map.build"):
        with open_map(path, cache_dir=str(tmp_path / "c"), progress=False) as m:
            check_exact(m, path)
            assert len(m.keys()) > 2
            assert max(m.node(k).count for k in m.keys()) <= build.LEAF_MAX + 128 ** 2
    assert any("bounds" in r.getMessage() and path in r.getMessage() for r in caplog.records)


def test_a_build_killed_midway_leaves_nothing_behind(tmp_path):
    """SIGKILL during the build (no cleanup runs): the next open removes the half-built
    folder and builds the index whole."""
    import glob
    import signal
    import subprocess
    import sys
    import time

    path = write_las(str(tmp_path / "t.laz"), 1_500_000, seed=17)
    cache = str(tmp_path / "cache")
    code = f"from pointflow.map import open_map; open_map({path!r}, cache_dir={cache!r}, progress=False)"
    proc = subprocess.Popen([sys.executable, "-c", code])
    try:
        deadline = time.monotonic() + 120
        while not glob.glob(os.path.join(cache, "*.tmp-*", "spill", "*")) and time.monotonic() < deadline:
            assert proc.poll() is None, "the build ended before it could be killed"
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait(30)
    assert glob.glob(os.path.join(cache, "*.tmp-*")), "no half-built index to clean up"
    with open_map(path, cache_dir=cache, progress=False) as m:
        assert m.point_count == 1_500_000
    assert os.listdir(cache) == [os.path.basename(m.files[0].dir)]


@pytest.mark.parametrize("kind", ["binary_big_endian", "ascii"])
def test_ply_big_endian_and_ascii(tmp_path, kind):
    import plyfile

    path = str(tmp_path / "t.ply")
    pos, ch = write_ply(path, 8_000, seed=18)
    ply = plyfile.PlyData.read(path, mmap=False)
    plyfile.PlyData(ply.elements, text=kind == "ascii", byte_order=">" if kind != "ascii" else "=").write(path)
    with open_map(path, cache_dir=str(tmp_path / "cache"), progress=False) as m:
        got, _ = all_nodes(m)
    og, ow = np.lexsort(got["positions"].T[::-1]), np.lexsort(pos.T[::-1])
    assert np.array_equal(got["positions"][og], pos[ow])
    assert np.array_equal(got["rgb"][og], ch["rgb"][ow])
    assert np.array_equal(got["intensity"][og], ch["intensity"][ow])


def test_binary_ply_streams_without_holding_the_file(tmp_path, monkeypatch):
    """A binary PLY is memory-mapped and indexed in chunks: the build's Python heap stays far
    below the file's size (the whole-file readers would hold all of it)."""
    import tracemalloc

    monkeypatch.setattr(inputs, "CHUNK_POINTS", 20_000)
    monkeypatch.setattr(build, "CHUNK_POINTS", 20_000)
    monkeypatch.setattr(build, "CELL_TARGET", 20_000)
    monkeypatch.setattr(build, "MAX_CELL", 60_000)
    # a coarser node grid: the cells' root points (held until the top is built, at most
    # cells x 128^2 for a flat map: a bound of its own, not the file's size) stay small here
    monkeypatch.setattr(build, "GRID_BITS", 3)
    monkeypatch.setattr(build, "LEAF_MAX", 5_000)
    write_ply(str(tmp_path / "warm.ply"), 1_000, seed=20)  # numba's first calls allocate; not the build's
    build.build_index(str(tmp_path / "warm.ply"), str(tmp_path / "cache" / "w"), progress=False)
    path = str(tmp_path / "big.ply")
    pos, _ = write_ply(path, 400_000, seed=19)
    size = os.path.getsize(path)
    tracemalloc.start()
    try:
        build.build_index(path, str(tmp_path / "cache" / "x"), progress=False)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < size / 2, (peak, size)
    with open_map(path, cache_dir=str(tmp_path / "cache2"), progress=False) as m:
        got, _ = all_nodes(m)
    assert np.array_equal(np.sort(got["positions"][:, 0]), np.sort(pos[:, 0]))
