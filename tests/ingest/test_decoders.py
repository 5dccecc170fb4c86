"""Quantised binary frames and JSON chunks: exact decoding and every rejection reason."""
import json
import struct

import numpy as np
import pytest

from pointflow.chunk import ChunkError
from pointflow.ingest.jsonchunk import chunk_to_json, parse_json_chunk
from pointflow.ingest.quantised import HEADER, AttributeRange, decode_quantised, encode_quantised

SCHEMA = [AttributeRange("intensity", 0.0, 255.0)]


def _frame(n, m=1, flags=0, xmin=(1.0, 2.0, 3.0), scale=10.0):
    q = np.arange(3 * n, dtype="<u2").reshape(n, 3) * 100
    a = np.full((n, m), 65535, "<u2")
    return HEADER.pack(n, m, flags, *xmin, scale) + q.tobytes() + a.tobytes(), q


def test_quantised_decoding_follows_the_spec():
    buf, q = _frame(5)
    c = decode_quantised(buf, SCHEMA)
    assert np.allclose(c.positions, np.array([1.0, 2.0, 3.0]) + q / 65535 * 10.0)
    assert np.allclose(c.channels["intensity"], 255.0)
    assert decode_quantised(HEADER.pack(0, 1, 0, 0, 0, 0, 1), SCHEMA).n == 0


@pytest.mark.parametrize("mutate,reason", [
    (lambda b: b[:-1], "truncated"),
    (lambda b: b[:10], "truncated"),
    (lambda b: b + b"\0\0", "size_mismatch"),
    (lambda b: b[:2] + bytes([2]) + b[3:], "schema_mismatch"),
    (lambda b: b[:3] + bytes([1]) + b[4:], "bad_flags"),
    (lambda b: b[:4] + struct.pack("<f", float("nan")) + b[8:], "bad_header"),
])
def test_quantised_rejections(mutate, reason):
    buf, _ = _frame(5)
    with pytest.raises(ChunkError) as e:
        decode_quantised(mutate(buf), SCHEMA)
    assert e.value.reason == reason


def test_quantised_round_trip_error_is_one_step():
    rng = np.random.default_rng(0)
    pos = rng.uniform(-1000, 1000, (1000, 3))
    inten = rng.uniform(0, 255, 1000)
    c = decode_quantised(encode_quantised(pos, {"intensity": inten}, SCHEMA), SCHEMA)
    scale = (pos.max(0) - pos.min(0)).max()
    assert np.abs(c.positions - pos).max() <= scale / 65535 * 0.5 + 1e-3
    assert np.abs(c.channels["intensity"] - inten).max() <= 255 / 65535 * 0.5 + 1e-4


@pytest.mark.parametrize("text,reason", [
    (b"\xff\xfe", "bad_json"),
    ("[1, 2]", "bad_shape"),
    ('{"nothing": 1}', "bad_shape"),
    ('{"points": [1, 2]}', "bad_shape"),
    ('{"points": [{"x": 1, "y": 2}]}', "bad_shape"),
    ('{"points": [{"x": "a", "y": 2, "z": 3}]}', "bad_dtype"),
    ('{"points": [{"x": 1, "y": 2, "z": 3, "i": 1}, {"x": 1, "y": 2, "z": 3}]}', "length_mismatch"),
    ('{"x": [1, 2], "y": [1], "z": [1, 2]}', "length_mismatch"),
    ('{"x": [1], "y": [1], "z": [1], "channels": {"i": [1, 2]}}', "length_mismatch"),
    ('{"x": [1], "y": [1], "z": [1], "channels": {"i": [[1, 2]]}}', "bad_shape"),
    ('{"positions": [[1, 2]]}', "bad_shape"),
    ('{"positions": [[1, 2, 3]], "channels": [1]}', "bad_shape"),
])
def test_json_rejections(text, reason):
    with pytest.raises(ChunkError) as e:
        parse_json_chunk(text)
    assert e.value.reason == reason


def test_json_too_large_and_both_shapes_agree():
    with pytest.raises(ChunkError, match="too_large"):
        parse_json_chunk(json.dumps({"x": [0] * 11, "y": [0] * 11, "z": [0] * 11}), max_points=10)
    from pointflow.chunk import PointChunk

    c = PointChunk(positions=np.arange(12.0).reshape(4, 3),
                   channels={"intensity": np.arange(4, dtype=np.float32), "rgb": np.full((4, 3), 7, np.uint8)})
    a = parse_json_chunk(chunk_to_json(c, columnar=True))
    b = parse_json_chunk(chunk_to_json(c, columnar=False))
    for x in (a, b):
        assert np.array_equal(x.positions, c.positions)
        assert np.array_equal(x.channels["intensity"], c.channels["intensity"])
        assert x.channels["rgb"].dtype == np.uint8 and np.array_equal(x.channels["rgb"], c.channels["rgb"])
