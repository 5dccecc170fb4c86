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
         "rgba": lambda: ru.cloud_rgb(6, rgba=True)}


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
