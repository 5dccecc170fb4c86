"""The frame id in the chunk header and the transforms message on the wire."""
import json

import numpy as np
import pytest

from pointflow import wire
from pointflow.chunk import PointChunk
from pointflow.frames import message as tfmsg
from pointflow.frames.message import Transform, TransformMessageError, Transforms


def test_frame_travels_in_the_header_and_old_senders_are_unchanged():
    c = PointChunk(positions=np.zeros((3, 3)), channels={"i": np.arange(3, dtype=np.float32)}, source_id="s",
                   seq=1, trace_id=2, t_sent_ns=3, stamp_ns=4)
    plain = wire.encode(c)
    head = json.loads(bytes(plain[0]))
    assert "frame" not in head and wire.decode(plain).frame_id == ""
    c.frame_id = "lidar_top"
    framed = wire.encode(c)
    assert json.loads(bytes(framed[0]))["frame"] == "lidar_top"
    d = wire.decode(framed)
    assert d.frame_id == "lidar_top" and d.stamp_ns == 4 and np.array_equal(d.channels["i"], c.channels["i"])


def test_transforms_message_round_trip_and_errors():
    b = Transforms([Transform("odom", "base", 5, (1, 2, 3), (0, 0, 0, 1)),
                    Transform("base", "lidar", 0, (0, 0, 1), (0, 0, 0, 1), True)], "src")
    (frame,) = tfmsg.encode(b)
    obj = json.loads(frame)
    assert tfmsg.is_transforms(obj) and tfmsg.SCHEMA_BYTES in frame
    back = tfmsg.decode(obj)
    assert back.source_id == "src" and back.transforms == [
        Transform("odom", "base", 5, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0)),
        Transform("base", "lidar", 0, (0.0, 0.0, 1.0), (0.0, 0.0, 0.0, 1.0), True)]
    for bad, where in [({"transforms": [{"parent": "a", "child": "b", "translation": [1, 2], "rotation": [0, 0, 0, 1]}]},
                        "transforms[0].translation"),
                       ({"transforms": [{"parent": "a", "child": "b", "stamp_ns": -1}]}, "transforms[0].stamp_ns"),
                       ({"transforms": [{"parent": "", "child": "b"}]}, "transforms[0]"),
                       ({"transforms": "x"}, "'transforms'")]:
        with pytest.raises(TransformMessageError) as e:
            tfmsg.decode({"schema": tfmsg.SCHEMA, **bad})
        assert e.value.reason == "bad_transform" and where in str(e.value)
