"""Bad map input: one line naming the file and what is wrong (MapError), or a rebuild with a
warning; never a traceback from laspy, lazrs or numpy."""
from __future__ import annotations

import os
import shutil
import struct
import subprocess

import laspy
import numpy as np
import pytest

from pointflow.map import MapError, NodeCache, open_map

from .mapfiles import write_copc, write_las


def expect_map_error(path, match, **kw):
    with pytest.raises(MapError) as ei:
        open_map(path, progress=False, **kw).close()
    msg = str(ei.value)
    assert "\n" not in msg and msg.startswith(str(path)) and match in msg, msg
    return msg


def test_truncated_laz(tmp_path):
    p = write_las(str(tmp_path / "t.laz"), 20_000)
    data = open(p, "rb").read()
    cut = str(tmp_path / "cut.laz")
    open(cut, "wb").write(data[: len(data) * 6 // 10])
    expect_map_error(cut, "not a valid LAS/LAZ file", cache_dir=str(tmp_path / "c"))


def test_truncated_las(tmp_path):
    p = write_las(str(tmp_path / "t.las"), 20_000)
    data = open(p, "rb").read()
    open(p, "wb").write(data[: len(data) // 2])
    expect_map_error(p, "header promises 20000 points", cache_dir=str(tmp_path / "c"))


def test_corrupt_laz_points(tmp_path):
    p = write_las(str(tmp_path / "t.laz"), 30_000)
    b = bytearray(open(p, "rb").read())
    for q in np.random.default_rng(0).integers(2000, len(b) - 2000, 50):
        b[q] ^= 0xFF
    open(p, "wb").write(b)
    expect_map_error(p, "not a valid LAS/LAZ file", cache_dir=str(tmp_path / "c"))
    assert not os.listdir(tmp_path / "c")  # the half-built index is gone


def test_not_a_point_cloud(tmp_path):
    p = tmp_path / "noise.las"
    p.write_bytes(os.urandom(4000))
    expect_map_error(str(p), "LASF", cache_dir=str(tmp_path / "c"))
    q = tmp_path / "cloud.xyz"
    q.write_text("1 2 3\n")
    expect_map_error(str(q), "COPC, LAS, LAZ, PLY or PCD", cache_dir=str(tmp_path / "c"))
    expect_map_error(str(tmp_path / "missing.laz"), "no such file", cache_dir=str(tmp_path / "c"))
    r = tmp_path / "bad.ply"
    r.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 100\nproperty float x\nend_header\n")
    expect_map_error(str(r), "PLY", cache_dir=str(tmp_path / "c"))


def _root_page(path):
    with laspy.CopcReader.open(path) as r:
        return r.copc_info.hierarchy_root_offset, r.copc_info.hierarchy_root_size


def test_copc_hierarchy_pointing_outside_the_file(tmp_path):
    p = write_copc(str(tmp_path / "t.copc.laz"), 10_000)
    off, size = _root_page(p)
    b = bytearray(open(p, "rb").read())
    d, x, y, z, eoff, esize, count = struct.unpack_from("<iiiiQii", b, off)
    struct.pack_into("<iiiiQii", b, off, d, x, y, z, 10 ** 12, esize, count)
    open(p, "wb").write(b)
    expect_map_error(p, "broken COPC hierarchy")


def test_copc_hierarchy_with_wrong_counts(tmp_path):
    p = write_copc(str(tmp_path / "t.copc.laz"), 10_000)
    off, size = _root_page(p)
    b = bytearray(open(p, "rb").read())
    d, x, y, z, eoff, esize, count = struct.unpack_from("<iiiiQii", b, off)
    struct.pack_into("<iiiiQii", b, off, d, x, y, z, eoff, esize, count + 7)
    open(p, "wb").write(b)
    expect_map_error(p, "broken COPC hierarchy")


def test_copc_hierarchy_with_a_bad_key_and_a_cut_page(tmp_path):
    p = write_copc(str(tmp_path / "t.copc.laz"), 10_000)
    off, size = _root_page(p)
    b = bytearray(open(p, "rb").read())
    struct.pack_into("<iiii", b, off, 1, 5, 0, 0)  # x = 5 at depth 1
    open(p, "wb").write(b)
    expect_map_error(p, "not an octree key")
    p2 = write_copc(str(tmp_path / "u.copc.laz"), 10_000)
    b = bytearray(open(p2, "rb").read())
    info_at = b.index(b"copc\0") - 2 + 54  # the info VLR's payload (first VLR after the header)
    struct.pack_into("<Q", b, info_at + 48, size - 5)  # root page size: not whole entries
    open(p2, "wb").write(b)
    expect_map_error(p2, "broken COPC hierarchy")


def test_truncated_copc(tmp_path):
    p = write_copc(str(tmp_path / "t.copc.laz"), 10_000)
    data = open(p, "rb").read()
    open(p, "wb").write(data[: len(data) // 2])
    expect_map_error(p, "not a valid")


def test_not_enough_disk_for_the_index(tmp_path):
    """A real small filesystem (tmpfs of 2 MiB) as the cache directory."""
    if os.geteuid() != 0 or not shutil.which("mount"):
        pytest.skip("mounting a small tmpfs needs root")
    mnt = tmp_path / "small"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mnt)], capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs here")
    try:
        p = write_las(str(tmp_path / "t.laz"), 50_000)
        msg = expect_map_error(p, "GiB are free", cache_dir=str(mnt / "cache"))
        assert str(mnt) in msg
    finally:
        subprocess.run(["umount", str(mnt)], check=True)


def test_a_node_bigger_than_the_cache_is_not_kept():
    c = NodeCache(1000)
    big = {"positions": np.zeros((100, 3))}
    assert c.put("a", big) is False and c.too_big == 1 and c.bytes_used == 0
    assert c.get("a") is None
    small = {"positions": np.zeros((10, 3))}
    assert c.put("b", small) and c.bytes_used == 240


def test_truncated_binary_ply(tmp_path):
    from .mapfiles import write_ply

    p = str(tmp_path / "t.ply")
    write_ply(p, 5_000)
    data = open(p, "rb").read()
    open(p, "wb").write(data[: len(data) * 2 // 3])
    expect_map_error(p, "PLY promises 5000 vertices", cache_dir=str(tmp_path / "c"))


def test_copc_with_random_damage_is_a_map_error_or_reads(tmp_path):
    """Bytes flipped in the hierarchy, the info VLR or a node's chunk: opening and loading
    every node either works or raises MapError; nothing else escapes (lazrs panics included)."""
    p = write_copc(str(tmp_path / "t.copc.laz"), 4_000, seed=5)
    off, size = _root_page(p)
    clean = open(p, "rb").read()
    info_at = clean.index(b"copc\0") - 2 + 54
    rng = np.random.default_rng(7)
    outcomes = {"ok": 0, "MapError": 0}
    for i in range(40):
        b = bytearray(clean)
        region = (off, off + size) if i % 3 == 0 else (info_at, info_at + 160) if i % 3 == 1 else (1000, off)
        for q in rng.integers(region[0], region[1], 1 + i % 4):
            b[q] ^= int(rng.integers(1, 256))
        path = tmp_path / f"d{i}.copc.laz"
        path.write_bytes(bytes(b))
        try:
            with open_map(str(path), progress=False) as m:
                for k in m.keys():
                    m.load(k)
            outcomes["ok"] += 1
        except MapError as exc:
            assert "\n" not in str(exc) and str(path) in str(exc)
            outcomes["MapError"] += 1
    assert outcomes["MapError"] > 0, outcomes


@pytest.mark.parametrize("ext", ["laz", "ply"])
def test_laz_and_ply_with_random_damage_are_a_map_error_or_read(tmp_path, ext):
    from .mapfiles import write_ply

    p = str(tmp_path / f"t.{ext}")
    write_las(p, 3_000, seed=6) if ext == "laz" else write_ply(p, 3_000, seed=6)
    clean = open(p, "rb").read()
    rng = np.random.default_rng(8)
    errors = 0
    for i in range(30):
        b = bytearray(clean)
        top = len(b) if i % 2 else min(len(b), 600)  # the header, or anywhere
        for q in rng.integers(0, top, 1 + i % 4):
            b[q] ^= int(rng.integers(1, 256))
        path = tmp_path / f"d{i}.{ext}"
        path.write_bytes(bytes(b))
        try:
            with open_map(str(path), cache_dir=str(tmp_path / "c"), progress=False) as m:
                for k in m.keys():
                    m.load(k)
        except MapError as exc:
            assert "\n" not in str(exc) and str(path) in str(exc)
            errors += 1
    assert errors > 0
