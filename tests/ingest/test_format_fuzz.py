"""Fuzz every file reader (issue 14.6, 14.7): from a valid file written here, at least 1,000
seeded mutations per format (truncations at random offsets, random byte flips, header
numbers set to 0, -1 or huge values). Each read yields valid points or a FormatError naming
the file; nothing else escapes. Then a real file-transport source stage given a few bad
files among good ones keeps going and sends every good point."""
from __future__ import annotations

import os
import re

import numpy as np
import pytest

from pointflow import formats
from pointflow.formats import FormatError, read as read_points

N_MUT = 1000
N_PTS = 40


def _points(seed=0):
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-50, 50, (N_PTS, 3)) + [637000.25, 849000.5, 400.0]
    return pos, rng.uniform(0, 255, N_PTS).astype(np.float32), rng.integers(0, 256, (N_PTS, 3)).astype(np.uint8)


def _write_las(path, compressed=False):
    import laspy

    pos, inten, rgb = _points(1)
    hdr = laspy.LasHeader(point_format=3, version="1.2")
    hdr.scales = [0.01, 0.01, 0.01]
    hdr.offsets = [637000.0, 849000.0, 0.0]
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = pos[:, 0], pos[:, 1], pos[:, 2]
    las.intensity = inten.astype(np.uint16)
    las.red, las.green, las.blue = (rgb.astype(np.uint16) * 257).T
    las.write(str(path))


def _write(fmt: str, path) -> None:
    pos, inten, rgb = _points(2)
    if fmt in ("las", "laz"):
        _write_las(path)
    elif fmt in ("ply", "ply_ascii"):
        formats.write_ply(str(path), pos, {"intensity": inten, "rgb": rgb}, binary=fmt == "ply")
    elif fmt in ("pcd", "pcd_ascii"):
        formats.write_pcd(str(path), pos, {"intensity": inten, "rgb": rgb}, binary=fmt == "pcd")
    elif fmt == "pcd_lzf":
        from .test_pcd_compressed import write_compressed

        write_compressed(str(path), ["x", "y", "z", "intensity"], [4, 4, 4, 4], ["F", "F", "F", "F"], [1, 1, 1, 1],
                         [pos[:, 0].astype("<f4"), pos[:, 1].astype("<f4"), pos[:, 2].astype("<f4"),
                          inten.astype("<f4")], len(pos))
    elif fmt == "npy":
        np.save(str(path), np.column_stack([pos, inten]))
    elif fmt == "npz":
        np.savez(str(path), xyz=pos, intensity=inten)
    elif fmt == "csv":
        np.savetxt(str(path), np.column_stack([pos, inten]), delimiter=",", header="x,y,z,intensity", comments="",
                   fmt="%.6f")
    elif fmt == "xyz":
        np.savetxt(str(path), pos, fmt="%.4f")
    elif fmt == "bin":
        np.column_stack([pos, inten]).astype("<f4").tofile(str(path))


EXT = {"las": "las", "laz": "laz", "ply": "ply", "ply_ascii": "ply", "pcd": "pcd", "pcd_ascii": "pcd", "pcd_lzf": "pcd", "npy": "npy",
       "npz": "npz", "csv": "csv", "xyz": "xyz", "bin": "bin"}
#: Bytes at the start that hold a header (where "set a header field" mutations aim).
HEADER_BYTES = {"las": 227, "laz": 227, "npy": 128, "zip": 200, "bin": 64}
SPECIAL_INTS = [0, -1, 0x7FFFFFFF, 0xFFFFFFFF, 0x80000000, 1 << 20]
SPECIAL_TOKENS = [b"0", b"-1", b"-99999", b"99999999999999", b"4294967296", b"1e308", b"nan", b"", b"x"]


def _header_len(fmt: str, data: bytes) -> int:
    for end, extra in ((b"end_header\n", 0), (b"\nDATA ascii\n", 0), (b"\nDATA binary\n", 0),
                       (b"\nDATA binary_compressed\n", 8)):  # + the two uint32 sizes
        i = data.find(end)
        if i >= 0:
            return min(len(data), i + len(end) + extra)
    if fmt in ("csv", "xyz"):
        return min(len(data), 200)
    return min(len(data), HEADER_BYTES.get(fmt, 64))


def _npz_mutations(good: bytes, rng: np.random.Generator, n: int):
    """Half of the npz mutations damage the archive, half the .npy members inside an intact one."""
    import io
    import zipfile

    with zipfile.ZipFile(io.BytesIO(good)) as z:
        members = {name: z.read(name) for name in z.namelist()}
    outer = mutations("zip", good, rng, n // 2)
    inner = {name: mutations("npy", data, rng, n) for name, data in members.items()}
    for i in range(n):
        if i % 2 == 0:
            yield next(outer)
            continue
        buf = io.BytesIO()
        victim = list(members)[i // 2 % len(members)]
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED if i % 4 == 1 else zipfile.ZIP_DEFLATED) as z:
            for name, data in members.items():
                z.writestr(name, next(inner[name]) if name == victim else data)
        yield buf.getvalue()


def mutations(fmt: str, good: bytes, rng: np.random.Generator, n: int):
    """n mutated files: truncations, byte flips, header numbers set to 0 / -1 / huge values."""
    if fmt == "npz":
        yield from _npz_mutations(good, rng, n)
        return
    hlen = _header_len(fmt, good)
    tokens = [m for m in re.finditer(rb"-?\d+(\.\d+)?(e[-+]?\d+)?", good[:hlen])]
    for i in range(n):
        kind = i % 4
        b = bytearray(good)
        if kind == 0:  # truncation at a random offset (often inside the header)
            cut = int(rng.integers(0, len(good))) if i % 8 else int(rng.integers(0, hlen + 1))
            b = b[:cut]
        elif kind == 1:  # random byte flips, anywhere
            for _ in range(int(rng.integers(1, 6))):
                b[int(rng.integers(0, len(b)))] = int(rng.integers(0, 256))
        elif kind == 2 and tokens:  # a number in a text header set to 0, negative, huge, garbage
            m = tokens[int(rng.integers(0, len(tokens)))]
            b = b[:m.start()] + SPECIAL_TOKENS[int(rng.integers(0, len(SPECIAL_TOKENS)))] + b[m.end():]
        else:  # a binary header word (u16/u32/u64 or f64) set to 0, negative or huge
            width = [2, 4, 8][int(rng.integers(0, 3))]
            at = int(rng.integers(0, max(1, hlen - width)))
            v = SPECIAL_INTS[int(rng.integers(0, len(SPECIAL_INTS)))]
            if width == 8 and rng.integers(0, 2):
                b[at:at + 8] = np.array([[0.0, -1e300, 1e308, np.inf, np.nan][int(rng.integers(0, 5))]], "<f8").tobytes()
            else:
                b[at:at + width] = (v & ((1 << (8 * width)) - 1)).to_bytes(width, "little")
        yield bytes(b)


def _check_points(pos, ch) -> int:
    assert isinstance(pos, np.ndarray) and pos.ndim == 2 and pos.shape[1] == 3, getattr(pos, "shape", pos)
    assert pos.dtype in (np.float32, np.float64)
    for k, v in ch.items():
        assert isinstance(v, np.ndarray) and v.shape[0] == pos.shape[0], (k, v.shape, pos.shape)
    return pos.shape[0]


@pytest.mark.timeout(120)
@pytest.mark.filterwarnings("error")  # no numpy overflow or empty-input warnings either
@pytest.mark.parametrize("fmt", list(EXT))
def test_every_mutation_reads_or_raises_format_error(tmp_path, fmt):
    good_path = tmp_path / f"good.{EXT[fmt]}"
    _write(fmt, good_path)
    good = good_path.read_bytes()
    pos, ch = read_points(str(good_path))
    assert _check_points(pos, ch) == N_PTS  # the unmutated file reads
    rng = np.random.default_rng(sum(map(ord, fmt)))
    p = tmp_path / f"m.{EXT[fmt]}"
    outcomes = {"points": 0, "error": 0}
    for data in mutations(fmt, good, rng, N_MUT):
        p.write_bytes(data)
        try:
            pos, ch = read_points(str(p))
        except FormatError as exc:
            assert str(exc).startswith(str(p) + ": ") and len(str(exc)) > len(str(p)) + 2
            outcomes["error"] += 1
            continue
        _check_points(pos, ch)
        outcomes["points"] += 1
    assert outcomes["error"] > 0  # the mutations do break files
    assert sum(outcomes.values()) == N_MUT


@pytest.mark.parametrize("ext", ["las", "laz"])
def test_malformed_las_is_a_format_error(tmp_path, ext):
    """All zero bytes and a truncated header: FormatError naming the file, not LaspyException."""
    zeros = tmp_path / f"zeros.{ext}"
    zeros.write_bytes(b"\0" * 4096)
    good = tmp_path / f"good.{ext}"
    _write_las(good)
    trunc = tmp_path / f"trunc.{ext}"
    trunc.write_bytes(good.read_bytes()[:100])
    for p in (zeros, trunc):
        with pytest.raises(FormatError, match=re.escape(str(p)) + r": not a valid LAS/LAZ file"):
            read_points(str(p))
        with pytest.raises(FormatError, match=re.escape(str(p))):
            list(formats.iter_las(str(p), 10))
        with pytest.raises(FormatError, match=re.escape(str(p))):
            formats.las_point_count(str(p))


def test_file_source_stage_skips_bad_files_and_sends_the_good_ones(tmp_path):
    """A real source process replaying a directory with broken files among good ones: it
    counts and skips each broken one, sends every good point, and ends normally."""
    import shutil

    import zmq

    from pointflow import wire

    from .test_source_stage import _start, _until_done

    d = tmp_path / "scans"
    d.mkdir()
    good = 0
    for name, fmt in (("a.ply", "ply"), ("c.npy", "npy"), ("e.bin", "bin"), ("g.las", "las")):
        _write(fmt, d / name)
        good += N_PTS
    (d / "b.las").write_bytes(b"\0" * 4096)                                   # all zero bytes
    (d / "d.pcd").write_bytes((d / "a.ply").read_bytes()[:60])                # not a PCD at all
    (d / "f.laz").write_bytes((d / "g.las").read_bytes()[:100])               # truncated header
    (d / "h.npz").write_bytes(b"PK\x03\x04" + bytes(200))                     # broken zip
    cfg = {"source": {"transport": "file", "options": {"path": str(d), "mode": "scans", "realtime": False}}}
    p, z, control, trace, ep, run_dir = _start(cfg)
    pull = z.socket(zmq.PULL)
    pull.bind(ep.ingest)
    try:
        chunks = []

        def take():
            while pull.poll(20):
                chunks.append(wire.decode(pull.recv_multipart()))

        msgs = _until_done(p, control, on_idle=take)
        take()
        assert p.exitcode == 0 and any(m["type"] == "done" for m in msgs)
        assert not [m for m in msgs if m["type"] == "error"]
        assert sum(c.n for c in chunks) == good
        last = [m for m in msgs if m["type"] == "heartbeat"][-1]["stats"]
        assert last["transport_bad_files"] == 4 and last["transport_files"] == 4
    finally:
        for s in (pull, control, trace):
            s.close(linger=0)
        z.term()
        shutil.rmtree(run_dir, ignore_errors=True)
