"""The file transport on real files of every format, written by the test."""
import os

import numpy as np
import pytest

from pointflow import formats
from pointflow.ingest.transports import resolve_transport
from pointflow.ingest.transports.base import InputUnreadable

N = 1234


def _data(seed=0):
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-100, 100, (N, 3)) + [637000.25, 849000.5, 400.0]  # georeferenced
    return pos, rng.uniform(0, 255, N).astype(np.float32), rng.integers(0, 256, (N, 3)).astype(np.uint8)


def _replay(path, **opts):
    cls = resolve_transport("file")
    o = cls.validate_options({"path": str(path), "realtime": False, **opts}, "sources[0].options", os.getcwd())
    t = cls(o, "f")
    t.open()
    try:
        return [c for c in t.chunks() if c is not None], t
    finally:
        t.close()


def _cat(chunks):
    return np.concatenate([c.positions for c in chunks]), {k: np.concatenate([c.channels[k] for c in chunks]) for k in chunks[0].channels}


def test_las_and_laz_keep_float64_and_channels(tmp_path):
    import laspy  # a test dependency (pointflow[formats]); a missing one must fail, not skip
    pos, inten, rgb = _data()
    for ext in ("las", "laz"):
        hdr = laspy.LasHeader(point_format=3, version="1.2")
        hdr.scales = [0.01, 0.01, 0.01]
        hdr.offsets = [637000.0, 849000.0, 0.0]
        las = laspy.LasData(hdr)
        las.x, las.y, las.z = pos[:, 0], pos[:, 1], pos[:, 2]
        las.intensity = inten.astype(np.uint16)
        las.classification = np.full(N, 2, np.uint8)
        las.gps_time = np.arange(N, dtype=np.float64)
        las.red, las.green, las.blue = (rgb.astype(np.uint16) * 257).T
        p = tmp_path / f"cloud.{ext}"
        las.write(str(p))
        chunks, t = _replay(p, chunk_points=500)
        assert [c.n for c in chunks] == [500, 500, 234]
        got, ch = _cat(chunks)
        assert got.dtype == np.float64 and np.abs(got - pos).max() <= 0.005 + 1e-9  # file precision, not float32's
        assert np.array_equal(ch["intensity"], inten.astype(np.uint16))
        assert np.array_equal(ch["gps_time"], np.arange(N))
        assert (ch["classification"] == 2).all()
        assert np.array_equal(ch["rgb"], rgb.astype(np.uint16) * 257)


@pytest.mark.parametrize("binary", [True, False])
def test_ply(tmp_path, binary):
    pos, inten, rgb = _data(1)
    p = tmp_path / "c.ply"
    formats.write_ply(str(p), pos, {"intensity": inten, "rgb": rgb}, binary=binary)
    got, ch = _cat(_replay(p)[0])
    assert np.allclose(got, pos, atol=1e-9)
    assert np.allclose(ch["intensity"], inten) and np.array_equal(ch["rgb"], rgb)


def test_ply_hand_written_ascii(tmp_path):
    p = tmp_path / "h.ply"
    p.write_text("ply\nformat ascii 1.0\ncomment by hand\nelement vertex 2\nproperty float x\nproperty float y\n"
                 "property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
                 "1 2 3 255 0 0\n4 5 6 0 255 0\n")
    got, ch = _cat(_replay(p)[0])
    assert np.array_equal(got, [[1, 2, 3], [4, 5, 6]]) and np.array_equal(ch["rgb"], [[255, 0, 0], [0, 255, 0]])


@pytest.mark.parametrize("binary", [True, False])
def test_pcd(tmp_path, binary):
    pos, inten, rgb = _data(2)
    pos = pos - [637000, 849000, 0]  # PCD stores float32
    p = tmp_path / "c.pcd"
    formats.write_pcd(str(p), pos, {"intensity": inten, **({"rgb": rgb} if binary else {})}, binary=binary)
    got, ch = _cat(_replay(p)[0])
    assert np.allclose(got, pos, atol=1e-4) and np.allclose(ch["intensity"], inten, atol=1e-3)
    if binary:
        assert np.array_equal(ch["rgb"], rgb)


def test_npy_npz_ouster_layout_kitti_csv(tmp_path):
    pos, inten, _ = _data(3)
    np.save(tmp_path / "a.npy", np.column_stack([pos, inten]))
    got, ch = _cat(_replay(tmp_path / "a.npy")[0])
    assert np.array_equal(got, pos) and np.allclose(ch["intensity"], inten)
    # Ouster-style npz: xyz float32, per-point range/reflectivity, per-column timestamps (skipped)
    np.savez(tmp_path / "o.npz", xyz=pos.astype(np.float32), range=np.arange(N, dtype=np.uint32),
             reflectivity=(np.arange(N) % 256).astype(np.uint8), timestamps_ns=np.arange(1024, dtype=np.uint64))
    chunks, _ = _replay(tmp_path / "o.npz", rename={"reflectivity": "intensity"})
    got, ch = _cat(chunks)
    assert got.dtype == np.float32 and set(ch) == {"range", "intensity"}
    assert np.array_equal(ch["intensity"], (np.arange(N) % 256).astype(np.uint8))
    # KITTI .bin: float32 x, y, z, reflectance
    k = np.column_stack([pos - [637000, 849000, 0], inten]).astype("<f4")
    k.tofile(tmp_path / "k.bin")
    got, ch = _cat(_replay(tmp_path / "k.bin")[0])
    assert np.array_equal(got, k[:, :3]) and np.array_equal(ch["intensity"], k[:, 3])
    # CSV with a header row, XYZ without
    np.savetxt(tmp_path / "c.csv", np.column_stack([pos, inten]), delimiter=",", header="x,y,z,intensity", comments="", fmt="%.6f")
    got, ch = _cat(_replay(tmp_path / "c.csv")[0])
    assert np.allclose(got, pos, atol=1e-6) and np.allclose(ch["intensity"], inten, atol=1e-5)
    np.savetxt(tmp_path / "p.xyz", pos, fmt="%.6f")
    got, _ = _cat(_replay(tmp_path / "p.xyz")[0])
    assert np.allclose(got, pos, atol=1e-6)


def test_scans_mode_directory_of_scans_in_order(tmp_path):
    for i in range(3):
        np.savez(tmp_path / f"scan{i}.npz", xyz=np.full((10 + i, 3), float(i), np.float32))
    chunks, t = _replay(tmp_path, rate=100)
    assert t.mode == "scans" and [c.n for c in chunks] == [10, 11, 12]
    assert [c.positions[0, 0] for c in chunks] == [0, 1, 2]


def test_bad_files_give_clear_errors(tmp_path, caplog):
    from pointflow.config import ConfigError

    cls = resolve_transport("file")
    with pytest.raises(ConfigError, match=r"sources\[0\]\.options\.path.*no such file"):
        cls.validate_options({"path": str(tmp_path / "missing.las")}, "sources[0].options", os.getcwd())
    (tmp_path / "x.bin").write_bytes(b"\0" * 10)
    with pytest.raises(formats.FormatError, match="x.bin.*multiple of 16"):
        formats.read(str(tmp_path / "x.bin"))
    (tmp_path / "t.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 100\nproperty float x\n"
                                     b"property float y\nproperty float z\nend_header\n" + b"\0" * 12)
    with pytest.raises(formats.FormatError, match="promises 100 vertices"):
        formats.read(str(tmp_path / "t.ply"))
    # a source none of whose files can be read fails, naming them and why (it used to
    # replay nothing and look like a success); looping over them too, instead of spinning
    for name, why, loop in (("x.bin", "multiple of 16", False), ("t.ply", "promises 100 vertices", False),
                            ("x.bin", "multiple of 16", True)):
        caplog.clear()
        with pytest.raises(InputUnreadable, match=rf"none of its 1 file\(s\) can be read: .*{name}.*{why}"):
            _replay(tmp_path / name, loop=loop)
        assert not [r for r in caplog.records if name in r.getMessage()]  # the error says it, once
    # one bad file among good ones is skipped (logged, counted), the others replayed
    d = tmp_path / "mixed"
    d.mkdir()
    np.save(d / "a_good.npy", np.zeros((5, 3), np.float32))
    (d / "b_bad.npy").write_bytes(b"not numpy")
    chunks, t = _replay(d, rate=1000)
    assert [c.n for c in chunks] == [5] and t.counters["bad_files"] == 1 and t.counters["files"] == 1
    # a bad file before any good one is said once a file was read (none read: the error says it)
    import logging

    (d / "0_bad.npy").write_bytes(b"not numpy either")
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="pointflow.transport.file"):
        chunks, t = _replay(d, rate=1000)
    said = [r.getMessage() for r in caplog.records if "skipped a file" in r.getMessage()]
    assert [c.n for c in chunks] == [5] and t.counters["bad_files"] == 2 and len(said) == 2, said
    assert "0_bad.npy" in said[0] and "b_bad.npy" in said[1], said


def test_progress_goes_to_the_progress_line_and_an_overrun_is_said_once(tmp_path, capsys, caplog):
    """Issue 31.7: the transport draws nothing itself (its bar and the run's progress line and
    log lines overwrote each other); its share sent is counted for the progress line, and the
    first time it sends more than the ring holds it warns, once, pointing to the remedy."""
    import logging

    pos, inten, _ = _data(5)
    np.save(tmp_path / "a.npy", np.column_stack([pos, inten]))
    cls = resolve_transport("file")
    o = cls.validate_options({"path": str(tmp_path / "a.npy"), "realtime": False, "chunk_points": 100},
                             "sources[0].options", os.getcwd())
    t = cls(o, "f")
    t.ring_capacity = 500  # as the source stage sets it: ring.max_points
    t.open()
    with caplog.at_level(logging.INFO, logger="pointflow.transport.file"):
        chunks = [c for c in t.chunks() if c is not None]
    t.close()
    assert sum(c.n for c in chunks) == N and t.counters["points"] == N and t.counters["total"] == N
    assert capsys.readouterr().err == ""  # nothing written around the logging
    said = [r for r in caplog.records if "more than the ring holds" in r.getMessage()]
    assert len(said) == 1 and said[0].levelno == logging.WARNING, [r.getMessage() for r in said]
    msg = said[0].getMessage()
    assert "a.npy has sent 600 points" in msg and "ring.max_points 500" in msg and f"of its {N:,} points" in msg
    assert "raise ring.max_points" in msg and "`map: {path: " in msg and "docs/map.md" in msg and "planned" not in msg
    _, quiet = _replay(tmp_path / "a.npy", progress="off")
    assert "total" not in quiet.counters  # not on the progress line


@pytest.mark.parametrize("size", [10, 4, 17, 31])
def test_a_short_kitti_file_is_reported_with_its_real_size(tmp_path, size):
    from pointflow.formats import FormatError
    from pointflow.formats.arrays import read_kitti

    p = tmp_path / "short.bin"
    p.write_bytes(bytes(range(size)))
    with pytest.raises(FormatError, match=rf"size {size} bytes is not a multiple of 16"):
        read_kitti(str(p))


# ---------------------------------------------------------------- pacing across loops
class _FakeTime:
    """Stands in for the ``time`` module of the playback clock: ``sleep`` moves the clock on,
    nothing else does, so release times are the schedule itself (no wall clock involved)."""

    def __init__(self):
        self.now = 1000.0

    def monotonic(self):
        return self.now

    def sleep(self, s):
        assert s >= 0
        self.now += s


def _release_times(monkeypatch, path, count, stall=None, **opts):
    """The fake-clock time each of the first ``count`` chunks went out (``stall``: {k: s},
    the consumer holds the replay s seconds after the k-th chunk, as a busy ingest would)."""
    from pointflow.ingest import playback

    fake = _FakeTime()
    monkeypatch.setattr(playback, "time", fake)
    cls = resolve_transport("file")
    o = cls.validate_options({"path": str(path), "loop": True, **opts}, "sources[0].options", os.getcwd())
    t = cls(o, "f")
    t.open()
    times, firsts = [], []
    try:
        for c in t.chunks():
            if c is None:
                continue
            times.append(fake.now)
            firsts.append(float(c.positions[0, 0]))
            if len(times) == count:
                break
            fake.now += (stall or {}).get(len(times), 0.0)
    finally:
        t.close()
    return np.array(times) - times[0], firsts, t


@pytest.mark.parametrize("n_files", [1, 3])
def test_scans_mode_loop_keeps_rate_across_the_loop(tmp_path, monkeypatch, n_files):
    """Every scan one period (1/rate) after the one before, also from the last file of a pass
    to the first of the next, and with a single file (each pass one scan)."""
    for i in range(n_files):
        np.save(tmp_path / f"scan{i}.npy", np.full((5, 3), float(i)))
    count = 3 * n_files + 4  # three loop boundaries at least
    times, firsts, t = _release_times(monkeypatch, tmp_path, count, mode="scans", rate=10.0)
    assert firsts == [float(i % n_files) for i in range(count)]  # the files in order, pass after pass
    assert t.counters["loops"] >= 3
    assert np.allclose(np.diff(times), 0.1, atol=1e-9), np.diff(times)
    assert np.allclose(times, 0.1 * np.arange(count), atol=1e-9)  # a schedule: no drift either


def test_stream_mode_loop_keeps_points_per_second_across_the_loop(tmp_path, monkeypatch):
    """stream mode: the last chunk's points take their time before the next pass starts."""
    np.save(tmp_path / "one.npy", np.arange(25 * 3, dtype=np.float64).reshape(25, 3))
    times, firsts, t = _release_times(monkeypatch, tmp_path / "one.npy", 10, mode="stream",
                                      points_per_second=100.0, chunk_points=10)
    # chunks of 10, 10, 5 points at 100 points/s: 0.1 s, 0.1 s, then 0.05 s to the next pass
    assert firsts == [0.0, 30.0, 60.0] * 3 + [0.0]
    assert np.allclose(times, [0, .1, .2, .25, .35, .45, .5, .6, .7, .75], atol=1e-9), times


def test_scans_mode_loop_after_a_stall_does_not_burst(tmp_path, monkeypatch):
    """A replay held back past the end of a pass (a busy ingest) starts the next pass at once
    and keeps the period from there, instead of rushing scans out to catch up."""
    for i in range(3):
        np.save(tmp_path / f"scan{i}.npy", np.full((5, 3), float(i)))
    times, _, _ = _release_times(monkeypatch, tmp_path, 7, stall={3: 5.0}, mode="scans", rate=10.0)
    assert np.allclose(times, [0, .1, .2, 5.2, 5.3, 5.4, 5.5], atol=1e-9), times
