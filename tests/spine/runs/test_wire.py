"""Wire format round trips through real ZeroMQ sockets, and its error reasons."""
import json

import numpy as np
import pytest
import zmq

from pointflow import wire
from pointflow.chunk import SUPPORTED_DTYPES, ChunkError, PointChunk


@pytest.fixture(scope="module")
def pair():
    ctx = zmq.Context()
    a, b = ctx.socket(zmq.PAIR), ctx.socket(zmq.PAIR)
    a.bind("inproc://wire-test")
    b.connect("inproc://wire-test")
    yield a, b
    a.close(); b.close(); ctx.term()


def _roundtrip(pair, chunk):
    a, b = pair
    wire.send(a, chunk)
    return wire.decode(b.recv_multipart(copy=False))


@pytest.mark.parametrize("pos_dtype", ["float32", "float64"])
@pytest.mark.parametrize("n", [0, 1, 1000, 70_000])  # 70k crosses the zero-copy threshold
def test_roundtrip_every_dtype(pair, pos_dtype, n):
    rng = np.random.default_rng(n)
    pos = (rng.normal(size=(n, 3)) * 1e3 + [6.4e5, 4.9e6, 100]).astype(pos_dtype)
    chans = {}
    for dt in SUPPORTED_DTYPES:
        info = np.iinfo(dt) if np.dtype(dt).kind in "iu" else None
        if info is not None:
            chans[dt] = rng.integers(info.min, info.max, size=n, dtype=dt, endpoint=True)
        else:
            chans[dt] = rng.normal(size=n).astype(dt)
    chans["rgb"] = rng.integers(0, 255, size=(n, 3), dtype=np.uint8)
    c = PointChunk(positions=pos, channels=chans, source_id="lidar0", seq=42, trace_id=7, t_sent_ns=123)
    d = _roundtrip(pair, c)
    assert d.n == n and d.source_id == "lidar0" and d.seq == 42 and d.trace_id == 7 and d.t_sent_ns == 123
    assert d.positions.dtype == np.dtype(pos_dtype)
    np.testing.assert_array_equal(d.positions, pos)
    assert list(d.channels) == list(chans)
    for k, v in chans.items():
        assert d.channels[k].dtype == v.dtype and d.channels[k].shape == v.shape
        np.testing.assert_array_equal(d.channels[k], v)


def test_noncontiguous_and_bigendian_inputs(pair):
    base = np.arange(30, dtype=">f8").reshape(10, 3)
    c = PointChunk(positions=base, channels={"i": np.arange(20, dtype=">i4")[::2]})
    d = _roundtrip(pair, c)
    np.testing.assert_array_equal(d.positions, base.astype("<f8"))
    np.testing.assert_array_equal(d.channels["i"], np.arange(0, 20, 2))


def _frames(n=4, pack=False):
    c = PointChunk(positions=np.zeros((n, 3), np.float32), channels={"intensity": np.ones(n, np.float32)})
    return [bytes(memoryview(f)) if not isinstance(f, bytes) else f for f in wire.encode(c, pack=pack)]


def _hdr(frames):
    return json.loads(frames[0])


@pytest.mark.parametrize("mutate,reason", [
    (lambda f: [b"{not json"] + f[1:], "bad_header"),
    (lambda f: [json.dumps({**_hdr(f), "schema": "x"}).encode()] + f[1:], "bad_schema"),
    (lambda f: [json.dumps({**_hdr(f), "n": -1}).encode()] + f[1:], "bad_count"),
    (lambda f: [json.dumps({**_hdr(f), "n": 5, "positions": {"dtype": "float32", "shape": [5, 3]}}).encode()] + f[1:], "truncated"),
    (lambda f: f[:1] + [f[1][:-4]] + f[2:], "truncated"),
    (lambda f: f[:1] + [f[1] + b"0000"] + f[2:], "size_mismatch"),
    (lambda f: f[:2], "bad_frame_count"),
    (lambda f: [json.dumps({**_hdr(f), "channels": [{"name": "intensity", "dtype": "complex64", "shape": [4]}]}).encode()] + f[1:], "bad_dtype"),
    (lambda f: [json.dumps({**_hdr(f), "channels": [{"name": "intensity", "dtype": "float32", "shape": [3]}]}).encode()] + f[1:], "length_mismatch"),
    (lambda f: [json.dumps({**_hdr(f), "positions": {"dtype": "int32", "shape": [4, 3]}}).encode()] + f[1:], "bad_dtype"),
    (lambda f: [b"\xff\xfe garbage"], "bad_frame_count"),
])
def test_malformed_messages_have_reasons(mutate, reason):
    with pytest.raises(ChunkError) as ei:
        wire.decode(mutate(_frames()))
    assert ei.value.reason == reason
    assert str(ei.value).startswith(reason)


@pytest.mark.parametrize("pos_dtype", ["float32", "float64"])
@pytest.mark.parametrize("n", [1, 3, 1000])
def test_small_chunks_go_packed_with_aligned_arrays(pair, pos_dtype, n):
    """Below PACK_MAX_BYTES the arrays travel in one data frame, each at a multiple of
    PACK_ALIGN; a big chunk, or pack=False, keeps a frame per array."""
    chans = {"a": np.arange(n, dtype=np.uint8), "b": np.arange(n, dtype=np.float64), "rgb": np.ones((n, 3), np.uint16)}
    c = PointChunk(positions=np.arange(3 * n, dtype=pos_dtype).reshape(n, 3), channels=chans, seq=9)
    frames = wire.encode(c)
    assert len(frames) == 2 and json.loads(frames[0])["packed"] is True
    body = bytes(frames[1])
    sizes = [c.positions.nbytes] + [a.nbytes for a in chans.values()]
    off = 0
    for a, nb in zip([c.positions, *chans.values()], sizes):
        off += -off % wire.PACK_ALIGN
        assert body[off:off + nb] == a.tobytes()
        off += nb
    assert len(body) == off
    d = _roundtrip(pair, c)
    np.testing.assert_array_equal(d.positions, c.positions)
    for k, v in chans.items():
        np.testing.assert_array_equal(d.channels[k], v)
        assert d.channels[k].ctypes.data % wire.PACK_ALIGN == d.positions.ctypes.data % wire.PACK_ALIGN
    assert len(wire.encode(c, pack=False)) == 2 + len(chans)
    big = PointChunk(positions=np.zeros((wire.PACK_MAX_BYTES // 12, 3), np.float32), channels={"i": np.zeros(wire.PACK_MAX_BYTES // 12, np.float32)})
    assert len(wire.encode(big)) == 3


@pytest.mark.parametrize("mutate,reason", [
    (lambda f: [f[0], f[1][:-1]], "truncated"),
    (lambda f: [f[0], f[1] + b"\0" * 8], "size_mismatch"),
    (lambda f: [f[0], f[1], f[1]], "bad_frame_count"),
    (lambda f: [f[0].replace(b'"packed":true', b'"packed":1'), f[1]], "bad_header"),
    (lambda f: [f[0].replace(b'"packed":true', b'"packed":true,"codec":"lz4"'), f[1]], "bad_header"),
    (lambda f: [f[0].replace(b'"shape":[4]', b'"shape":[5]'), f[1]], "length_mismatch"),
    (lambda f: [f[0].replace(b'"dtype":"float32","shape":[4]', b'"dtype":"complex64","shape":[4]'), f[1]], "bad_dtype"),
])
def test_malformed_packed_messages_have_reasons(mutate, reason):
    frames = _frames(pack=True)
    assert len(frames) == 2
    with pytest.raises(ChunkError) as ei:
        wire.decode(mutate(frames))
    assert ei.value.reason == reason


def test_encode_fast_path_equals_the_general_one():
    """encode() fills a cached header template per stream; it must give what the general path
    (a dict through _header_json) gives, byte for byte, '%' in names included."""
    rng = np.random.default_rng(3)
    for i in range(200):
        n = int(rng.choice([0, 1, 5, 1000, 6000]))
        chans = {str(k): rng.integers(0, 99, (n, 3) if k == "rgb" else n).astype(rng.choice(["uint8", "float32", "float64"]))
                 for k in rng.choice(["i", "rgb", "%d", "t%s"], size=int(rng.integers(0, 3)), replace=False)}
        c = PointChunk(positions=rng.normal(size=(n, 3)).astype(rng.choice(["float32", "float64"])), channels=chans,
                       source_id=str(rng.choice(["s", "100%", "%d%%"])), seq=int(rng.integers(0, 2**40)),
                       trace_id=int(rng.integers(0, 2**63)), t_sent_ns=int(rng.integers(1, 2**62)),
                       stamp_ns=int(rng.choice([0, 5])), frame_id=str(rng.choice(["", "f%", "odom"])))
        for pack in (True, False):
            for _ in range(2):  # the second time from the cached template
                fast = [bytes(memoryview(f)) for f in wire.encode(c, pack=pack)]
                assert fast == [bytes(memoryview(f)) for f in wire._encode_general(c, pack)], (i, fast[0])


def test_max_points_rejects_before_reading_frames():
    with pytest.raises(ChunkError) as ei:
        wire.decode(_frames(10), max_points=5)
    assert ei.value.reason == "too_large"


def test_chunk_validate_names_the_channel():
    c = PointChunk(positions=np.zeros((3, 3)), channels={"intensity": np.zeros(2)})
    with pytest.raises(ChunkError, match="intensity") as ei:
        c.validate()
    assert ei.value.reason == "length_mismatch"


# ---- fast paths (perf): must match the straightforward implementation exactly ----------------
@pytest.mark.parametrize("source", ["bench", "", "lidär/ø", 'q"uo\\te\n', 7, None])
@pytest.mark.parametrize("names", [(), ("intensity",), ("rgb", "classification"), ("ünï\tcode",)])
def test_header_bytes_equal_json_dumps(source, names):
    rng = np.random.default_rng(0)
    chans = {}
    for i, name in enumerate(names):
        chans[name] = rng.integers(0, 255, (5, 3) if name == "rgb" else 5).astype(SUPPORTED_DTYPES[i % len(SUPPORTED_DTYPES)])
    for dt, stamp, frame in (("float32", 0, ""), ("float64", 5, "lidar"), (">f8", 0, 'ö"d\\')):
        c = PointChunk(positions=np.zeros((5, 3), dt), channels=chans, source_id=source, seq=2**40 + 3,
                       trace_id=2**63 + 11, t_sent_ns=123456789, stamp_ns=stamp, frame_id=frame)
        frames = wire.encode(c)
        h = json.loads(frames[0])
        assert frames[0] == json.dumps(h, separators=(",", ":")).encode()
        assert h.get("frame", "") == frame and h.get("stamp_ns", 0) == stamp
        assert h["source"] == source and h["seq"] == 2**40 + 3 and h["trace"] == 2**63 + 11
        assert [ch["name"] for ch in h["channels"]] == list(names)
        assert h["positions"]["dtype"] == np.dtype(dt).name


def test_header_non_str_channel_name_falls_back_to_json_dumps():
    c = PointChunk(positions=np.zeros((2, 3)), channels={5: np.zeros(2, np.float32)})
    frames = wire.encode(c)
    h = json.loads(frames[0])
    assert h["channels"][0]["name"] == 5
    assert frames[0] == json.dumps(h, separators=(",", ":")).encode()


def _old_expected(shape, itemsize):
    return int(np.prod(shape, dtype=np.int64)) * itemsize


@pytest.mark.parametrize("shape", [[2**39, 2**39], [2**39, 2**25], [2**39, 2**24 + 1], [3, 2**39], [0, 5], [7]])
def test_frame_size_product_wraps_like_int64(shape):
    # wire._array checks the frame against the int64 product of the shape (as np.prod gave),
    # also when that overflows (not reachable through decode: the positions frame is checked first)
    exp = _old_expected(shape, 1)
    frame = b"\0" * exp if 0 <= exp < 1000 else b"\0" * 8
    if 0 <= exp < 1000:
        try:
            wire._array(frame, "uint8", shape, "c")
        except ValueError as e:  # reshape of a wrapped size: what decode reports as decode_error
            assert not isinstance(e, ChunkError)
    else:
        with pytest.raises(ChunkError) as ei:
            wire._array(frame, "uint8", shape, "c")
        assert ei.value.reason == ("truncated" if exp > 8 else "size_mismatch")


def _outcome(fn, frames, max_points):
    try:
        c = fn(frames, max_points)
    except ChunkError as exc:
        return ("error", exc.reason, str(exc))
    return ("ok", c.source_id, c.seq, c.trace_id, c.t_sent_ns, c.stamp_ns, c.frame_id, c.positions.dtype.str,
            c.positions.tobytes(), [(k, v.dtype.str, v.shape, v.tobytes()) for k, v in c.channels.items()])


def test_fast_decode_equals_the_full_parse_on_good_and_bad_headers(pair):
    """decode() skips the JSON parse for headers laid out as encode() writes them; for every
    message, good or damaged, bytes or zmq.Frame, it must give what decode_message gives
    (same chunk, or the same reason and message)."""
    rng = np.random.default_rng(7)
    taken = 0
    for i in range(600):
        n = int(rng.integers(0, 40))
        chans = {}
        for name in rng.choice(["intensity", "rgb", "t", "ring"], size=int(rng.integers(0, 3)), replace=False):
            shape = (n, 3) if name == "rgb" else (n,)
            chans[str(name)] = rng.integers(0, 255, shape).astype(rng.choice(["uint8", "uint16", "float32", "float64"]))
        chunk = PointChunk(positions=rng.normal(size=(n, 3)).astype(rng.choice(["float32", "float64"])), channels=chans,
                           source_id=str(rng.choice(["lidar", "", 'a"b', "l\u00e4", "x\\y"])), seq=int(rng.integers(0, 2**40)),
                           trace_id=int(rng.integers(0, 2**63)), stamp_ns=int(rng.choice([0, int(rng.integers(1, 2**62))])),
                           frame_id=str(rng.choice(["", "", "lidar_top", 'f"r', "b\u00e4se", "x\\y", ",\"frame\":\"", "odom", "a]b", "]"])))
        frames = [bytes(f) for f in wire.encode(chunk, pack=bool(rng.integers(2)))]
        kind = i % 10
        if kind == 1:  # random byte flips anywhere
            j = int(rng.integers(len(frames)))
            b = bytearray(frames[j])
            for _ in range(3):
                if b:
                    b[int(rng.integers(len(b)))] = int(rng.integers(256))
            frames[j] = bytes(b)
        elif kind == 2:
            frames = frames[:-1]
        elif kind == 3:
            frames[1] = frames[1][:-4]
        elif kind == 4:  # a repeated key after the fixed ones: json.loads keeps the last
            frames[0] = frames[0].replace(b'"n":', b'"seq":5,"source":"other","n":')
        elif kind == 5:  # an extra key after the capture stamp
            frames[0] = frames[0][:-1] + b',"stamp_ns":12,"extra":1}'
        elif kind == 6:
            frames[0] = frames[0].replace(b'"seq":', b'"seq":0', 1)  # leading zero: not JSON
        elif kind == 7:  # the frame id before the stamp, or twice, or not a string
            frames[0] = frames[0][:-1] + rng.choice([b',"frame":"a","stamp_ns":3}', b',"frame":"a","frame":"b"}',
                                                     b',"frame":7}', b',"frame":"a"}', b',"frame":"a\\"}'])
        max_points = [None, 10, 100][i % 3]
        for as_frames in (False, True):
            msg = frames
            if as_frames:
                pair[0].send_multipart(frames)
                msg = pair[1].recv_multipart(copy=False)
            fast = wire._decode_fast(msg, max_points)
            taken += fast is not None
            if fast is not None and not as_frames:
                assert not fast.positions.flags.writeable  # views on bytes stay read-only
            assert _outcome(wire.decode, msg, max_points) == _outcome(lambda f, m: wire.decode_message(f, m)[0], msg, max_points), (i, frames[0])
    assert taken > 40  # undamaged, small enough, plain source and frame names: the fast path
