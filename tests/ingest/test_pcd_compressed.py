"""PCD ``DATA binary_compressed`` (PCL's default when saving compressed): written by the test
with the real LZF binding, read back equal to the same cloud saved uncompressed."""
import os
import struct

import numpy as np
import pytest

from pointflow import formats
from pointflow.ingest.transports import resolve_transport

N = 777


def _cloud(seed=0):
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-50, 50, (N, 3)).astype(np.float32)
    return pos, rng.uniform(0, 255, N).astype(np.float32), rng.integers(0, 256, (N, 3)).astype(np.uint8)


def write_compressed(path, names, sizes, types, counts, columns, n, tamper=None):
    """A binary_compressed PCD: header, uint32 compressed size, uint32 raw size, LZF of the
    fields stored column after column (as PCL writes it)."""
    import lzf

    raw = b"".join(np.ascontiguousarray(c).tobytes() for c in columns)
    comp = lzf.compress(raw, len(raw) + len(raw) // 16 + 64)  # random floats barely compress
    csize, usize = len(comp), len(raw)
    if tamper == "usize":
        usize += 4
    if tamper == "short":
        comp = comp[: len(comp) // 2]
    if tamper == "corrupt":
        comp = bytes([comp[0] ^ 0xFF]) + comp[1:]
    head = ["VERSION .7", "FIELDS " + " ".join(names), "SIZE " + " ".join(map(str, sizes)),
            "TYPE " + " ".join(types), "COUNT " + " ".join(map(str, counts)), f"WIDTH {n}", "HEIGHT 1",
            "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {n}", "DATA binary_compressed"]
    with open(path, "wb") as f:
        f.write(("\n".join(head) + "\n").encode() + struct.pack("<II", csize, usize) + comp)


def _pcl_layout(pos, inten, rgb):
    u = (rgb[:, 0].astype(np.uint32) << 16) | (rgb[:, 1].astype(np.uint32) << 8) | rgb[:, 2].astype(np.uint32)
    return (["x", "y", "z", "intensity", "rgb"], [4] * 5, ["F"] * 5, [1] * 5,
            [pos[:, 0], pos[:, 1], pos[:, 2], inten, u.view(np.float32)])


def test_compressed_equals_uncompressed(tmp_path):
    pos, inten, rgb = _cloud()
    formats.write_pcd(str(tmp_path / "plain.pcd"), pos, {"intensity": inten, "rgb": rgb}, binary=True)
    write_compressed(tmp_path / "packed.pcd", *_pcl_layout(pos, inten, rgb), N)
    assert os.path.getsize(tmp_path / "packed.pcd") != os.path.getsize(tmp_path / "plain.pcd")
    p0, c0 = formats.read(str(tmp_path / "plain.pcd"))
    p1, c1 = formats.read(str(tmp_path / "packed.pcd"))
    assert np.array_equal(p0, p1) and np.array_equal(p1, pos.astype(np.float64))
    assert set(c0) == set(c1) == {"intensity", "rgb"}
    assert all(np.array_equal(c0[k], c1[k]) for k in c0)
    assert np.array_equal(c1["rgb"], rgb)
    # and through the file transport
    cls = resolve_transport("file")
    t = cls(cls.validate_options({"path": str(tmp_path / "packed.pcd"), "realtime": False}, "s", os.getcwd()), "f")
    t.open()
    chunks = [c for c in t.chunks() if c is not None]
    t.close()
    assert np.array_equal(np.concatenate([c.positions for c in chunks]), p0)


def test_compressed_mixed_sizes_counts_and_padding(tmp_path):
    rng = np.random.default_rng(1)
    pos = rng.uniform(-5, 5, (N, 3))
    ring = rng.integers(0, 128, N).astype(np.uint16)
    normal = rng.uniform(-1, 1, (N, 3)).astype(np.float32)
    pad = np.zeros((N, 2), np.uint8)
    write_compressed(tmp_path / "m.pcd", ["x", "y", "z", "ring", "normal", "_"], [8, 8, 8, 2, 4, 1],
                     ["F", "F", "F", "U", "F", "U"], [1, 1, 1, 1, 3, 2],
                     [pos[:, 0], pos[:, 1], pos[:, 2], ring, normal, pad], N)
    got, ch = formats.read(str(tmp_path / "m.pcd"))
    assert np.array_equal(got, pos) and np.array_equal(ch["ring"], ring)


@pytest.mark.parametrize("tamper,msg", [("usize", "promises 15544 uncompressed bytes; 777 points of 20 bytes are 15540"),
                                        ("short", "promises \\d+ compressed bytes, file has \\d+"),
                                        ("corrupt", "(data is not valid LZF|data does not decompress to the promised)")])
def test_compressed_sizes_promised_vs_present_are_checked(tmp_path, tamper, msg):
    pos, inten, rgb = _cloud(2)
    names, sizes, types, counts, cols = _pcl_layout(pos, inten, rgb)
    write_compressed(tmp_path / "bad.pcd", names, sizes, types, counts, cols, N, tamper=tamper)
    with pytest.raises(formats.FormatError, match="bad.pcd: PCD binary_compressed " + msg):
        formats.read(str(tmp_path / "bad.pcd"))
