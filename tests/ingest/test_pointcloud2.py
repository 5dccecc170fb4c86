"""The PointCloud2 decoder on every layout peers get wrong, against clouds packed point by
point with ``struct`` (tests/ingest/ros_util.py), as rosbridge dicts and as rosbags messages
that went through real CDR / ROS 1 serialisation."""
import base64
import dataclasses

import numpy as np
import pytest

from pointflow.chunk import ChunkError
from pointflow.ingest.pointcloud2 import PointCloud2Decoder, decode

from . import ros_util as ru

CASES = {"padded": ru.cloud_padded, "bigendian": ru.cloud_bigendian, "unsorted": ru.cloud_unsorted,
         "count": ru.cloud_count, "organised": ru.cloud_organised, "rgb": ru.cloud_rgb,
         "rgba": lambda: ru.cloud_rgb(6, rgba=True), "rgba_bigendian": lambda: ru.cloud_rgb(7, rgba=True, big=True)}


def assert_matches(chunk, cloud, rename=None):
    pos, ch = cloud.expected()
    rename = rename or {}
    assert chunk.positions.shape == (cloud.n, 3)
    assert chunk.positions.dtype == (np.float64 if cloud.values["x"].dtype == np.float64 else np.float32)
    assert np.array_equal(chunk.positions, pos, equal_nan=True)
    want = {rename.get(k, k): v for k, v in ch.items()}
    assert set(chunk.channels) == set(want)
    for k, v in want.items():
        got = chunk.channels[k]
        assert got.dtype == v.dtype and got.shape == v.shape, k
        assert np.array_equal(got, v), k
        assert got.flags.c_contiguous and got.dtype.isnative
    assert chunk.stamp_ns == cloud.stamp_ns


@pytest.mark.parametrize("case", sorted(CASES))
def test_layouts_decode_exactly_from_a_rosbridge_dict(case):
    cloud = CASES[case]()
    assert_matches(decode(cloud.as_dict()), cloud)
    assert_matches(decode(cloud.as_dict(ros1=True, data=base64.b64encode(cloud.data).decode())), cloud)


@pytest.mark.parametrize("store", ["ROS2_HUMBLE", "ROS1_NOETIC"])
def test_layouts_decode_exactly_after_real_serialisation(store):
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(getattr(Stores, store))
    for case, make in CASES.items():
        cloud = make()
        msg = cloud.ros_msg(ts)
        if store == "ROS1_NOETIC":
            back = ts.deserialize_ros1(ts.serialize_ros1(msg, ru.PC2), ru.PC2)
        else:
            back = ts.deserialize_cdr(ts.serialize_cdr(msg, ru.PC2), ru.PC2)
        assert_matches(decode(back), cloud)


def test_organised_nan_points_are_passed_on_for_ingest_to_count():
    cloud = ru.cloud_organised()
    c = decode(cloud.as_dict())
    bad = ~np.isfinite(c.positions).all(axis=1)
    assert bad.sum() == 16 + 6  # row 1 (16 points) + the scattered z misses outside it
    assert bad[16:32].all()


def test_packed_colour_nan_bit_patterns_survive():
    cloud = ru.cloud_rgb(6, rgba=True)
    assert np.isnan(cloud.values["rgba"]).sum() >= 5  # alpha 0xFF and red >= 128: the float is a NaN
    c = decode(cloud.as_dict())
    assert np.array_equal(c.channels["rgb"], cloud.expected()[1]["rgb"])


def test_data_as_a_list_of_ints_or_a_cbor_typed_array_tag():
    import cbor2

    cloud = ru.cloud_padded(n=6)
    assert_matches(decode(cloud.as_dict(data=list(cloud.data))), cloud)  # older rosbridge JSON
    assert_matches(decode(cloud.as_dict(data=cbor2.CBORTag(64, cloud.data))), cloud)  # RFC 8746 uint8 array
    with pytest.raises(ChunkError, match="bytes 0..255") as e:
        decode(cloud.as_dict(data=[1, 2, 300]))
    assert e.value.reason == "bad_data"


def test_rename_and_channel_filter_choose_what_is_copied():
    cloud = ru.cloud_padded()
    c = decode(cloud.as_dict(), rename={"reflectivity": "refl", "intensity": "power"}, channels=["refl", "ring"])
    assert set(c.channels) == {"refl", "ring"}
    assert np.array_equal(c.channels["refl"], cloud.values["reflectivity"])
    c = decode(ru.cloud_rgb().as_dict(), channels=["intensity"])  # rgb not wanted: not unpacked
    assert c.channels == {}


def test_separate_r_g_b_fields_become_the_rgb_channel():
    rng = np.random.default_rng(0)
    n = 10
    v = {"x": rng.random(n).astype(np.float32), "y": rng.random(n).astype(np.float32),
         "z": rng.random(n).astype(np.float32), "r": rng.integers(0, 255, n).astype(np.uint8),
         "g": rng.integers(0, 255, n).astype(np.uint8), "b": rng.integers(0, 255, n).astype(np.uint8)}
    f = [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("r", 12, 2, 1), ("g", 13, 2, 1), ("b", 14, 2, 1)]
    c = decode(ru.pack(f, 16, n, 1, v).as_dict())
    assert set(c.channels) == {"rgb"}
    assert np.array_equal(c.channels["rgb"], np.column_stack([v["r"], v["g"], v["b"]]))


def test_empty_cloud_is_an_empty_chunk():
    cloud = ru.cloud_padded(n=4)
    c = decode(dataclasses.replace(cloud, width=0, row_step=0, data=b"").as_dict())
    assert c.n == 0 and c.positions.shape == (0, 3) and c.channels["ring"].shape == (0,)


def test_layout_plan_is_reused_and_rebuilt_when_the_layout_changes():
    d = PointCloud2Decoder()
    a, b = ru.cloud_padded(1), ru.cloud_padded(2)
    assert_matches(d.decode(a.as_dict()), a)
    plan = d._plan
    assert_matches(d.decode(b.as_dict()), b)
    assert d._plan is plan
    u = ru.cloud_unsorted()
    assert_matches(d.decode(u.as_dict()), u)
    assert d._plan is not plan


@pytest.mark.parametrize("kind,field", [("truncated", "'data'"), ("field_overflow", "'range'"),
                                        ("unknown_datatype", "'intensity'"), ("no_xyz", "'z'")])
def test_every_rejection_names_its_field(kind, field):
    with pytest.raises(ChunkError) as e:
        decode(ru.broken(kind).as_dict())
    assert e.value.reason == kind and field in str(e.value)


def test_other_defects_are_rejected_with_reasons():
    c = ru.cloud_organised()
    with pytest.raises(ChunkError, match="row_step 10 is smaller") as e:
        decode(dataclasses.replace(c, row_step=10).as_dict())
    assert e.value.reason == "bad_layout"
    with pytest.raises(ChunkError, match="'x' is listed twice") as e:
        decode(dataclasses.replace(c, fields=c.fields + [("x", 0, 7, 1)]).as_dict())
    assert e.value.reason == "bad_field"
    with pytest.raises(ChunkError, match="not valid base64") as e:
        decode(c.as_dict(data="***"))
    assert e.value.reason == "bad_data"
    d = c.as_dict()
    del d["point_step"]
    with pytest.raises(ChunkError, match="no 'point_step'") as e:
        decode(d)
    assert e.value.reason == "bad_shape"
    with pytest.raises(ChunkError, match="'x' has count 2") as e:
        decode(dataclasses.replace(c, fields=[("x", 0, 7, 2)] + c.fields[1:]).as_dict())
    assert e.value.reason == "no_xyz"


from hypothesis import given, settings, strategies as st  # noqa: E402

_field = st.tuples(st.sampled_from(["x", "y", "z", "intensity", "rgb", "rgba", "ring", "", "t"]),
                   st.integers(-8, 64), st.integers(-1, 10), st.integers(-1, 4))


_xyz = st.tuples(st.integers(0, 40), st.sampled_from([7, 7, 8, 2, 5]))


@settings(max_examples=500, deadline=None)
@given(xyz=st.lists(_xyz, min_size=3, max_size=3), drop=st.sampled_from([None, None, None, "x", "z"]),
       extra=st.lists(_field, max_size=5), point_step=st.integers(-4, 64), width=st.integers(-2, 9),
       height=st.integers(-1, 4), row_extra=st.integers(-70, 40), data_len=st.integers(0, 2000), big=st.booleans())
def test_any_layout_decodes_or_is_rejected_with_a_reason(xyz, drop, extra, point_step, width, height, row_extra,
                                                         data_len, big):
    """Whatever a publisher sends, the decoder returns a consistent chunk or raises ChunkError."""
    fields = [(k, o, d, 1) for k, (o, d) in zip("xyz", xyz) if k != drop] + extra
    msg = {"header": {"stamp": {"sec": 1, "nanosec": 2}}, "width": width, "height": height,
           "fields": [{"name": n, "offset": o, "datatype": d, "count": c} for n, o, d, c in fields],
           "is_bigendian": big, "point_step": point_step, "row_step": max(0, width) * point_step + row_extra,
           "data": bytes(range(256)) * (data_len // 256) + bytes(data_len % 256)}
    try:
        c = decode(msg)
    except ChunkError as exc:
        assert exc.reason in {"truncated", "field_overflow", "unknown_datatype", "no_xyz", "bad_field", "bad_layout"}
        return
    c.validate()
    assert c.n == width * height and c.stamp_ns == 1_000_000_002


_LIMITS = {1: (-128, 127), 2: (0, 255), 3: (-32768, 32767), 4: (0, 65535), 5: (-2**31, 2**31 - 1),
           6: (0, 2**32 - 1)}


@settings(max_examples=300, deadline=None)
@given(data=st.data(), xyz_types=st.lists(st.sampled_from([7, 7, 7, 8, 3, 5]), min_size=3, max_size=3),
       extra=st.lists(st.tuples(st.integers(1, 8), st.integers(1, 3)), max_size=4), width=st.integers(0, 6),
       height=st.integers(1, 3), row_pad=st.integers(0, 9), tail_pad=st.integers(0, 9), big=st.booleans(),
       seed=st.integers(0, 2**31))
def test_random_valid_layouts_decode_like_the_struct_packer(data, xyz_types, extra, width, height, row_pad, tail_pad,
                                                             big, seed):
    """Random fields (types, counts, order, gaps, padding, endianness, row padding) packed point
    by point with struct: the decoder returns exactly those values."""
    rng = np.random.default_rng(seed)
    specs = [(k, t, 1) for k, t in zip("xyz", xyz_types)] + [(f"f{i}", t, c) for i, (t, c) in enumerate(extra)]
    order = data.draw(st.permutations(range(len(specs))))
    fields, off = [], 0
    for j in order:  # laid out in a random order with random gaps; listed in another random order
        name, t, c = specs[j]
        off += data.draw(st.integers(0, 3))
        fields.append((name, off, t, c))
        off += ru.DT[t][1]().itemsize * c
    fields = data.draw(st.permutations(fields))
    n = width * height
    values = {}
    for name, _, t, c in fields:
        shape = (n,) if c == 1 else (n, c)
        if t in (7, 8):
            values[name] = (rng.integers(-2**20, 2**20, shape) / 64).astype(ru.DT[t][1])
        else:
            lo, hi = _LIMITS[t]
            values[name] = rng.integers(lo, hi, shape, endpoint=True).astype(ru.DT[t][1])
    cloud = ru.pack(fields, off + tail_pad, width, height, values, big=big, row_pad=row_pad)
    c = decode(cloud.as_dict())
    pos, ch = cloud.expected()
    assert c.positions.dtype == (np.float32 if xyz_types == [7, 7, 7] else np.float64)
    assert np.array_equal(c.positions, pos.astype(np.float64))
    assert set(c.channels) == set(ch)
    for k, v in ch.items():
        assert c.channels[k].dtype == v.dtype and np.array_equal(c.channels[k], v), k


def test_header_stamp_travels_in_the_wire_header():
    import json

    from pointflow import wire

    cloud = ru.cloud_padded(n=5)
    frames = wire.encode(decode(cloud.as_dict(), source_id="bag:/os/points"))
    head = json.loads(bytes(frames[0]))
    assert head["stamp_ns"] == cloud.stamp_ns
    assert bytes(frames[0]) == json.dumps(head, separators=(",", ":")).encode()  # the fast path's bytes
    assert wire.decode(frames).stamp_ns == cloud.stamp_ns
    frames = wire.encode(decode(dataclasses.replace(cloud, stamp=(0, 0)).as_dict()))
    assert "stamp_ns" not in json.loads(bytes(frames[0]))  # unknown: not sent
