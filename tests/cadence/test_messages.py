"""Render -> cadence control messages: round trip, and clear errors for malformed ones."""
import json

import pytest

from pointflow.cadence.messages import (
    CONTROL_TAG,
    ControlMessageError,
    FrameTime,
    Hello,
    Idle,
    decode_control,
    encode_frame_time,
    encode_hello,
    encode_idle,
)


def test_round_trip():
    assert decode_control(encode_hello(1234, 2)) == Hello(pid=1234, restart_count=2)
    assert decode_control(encode_frame_time(16.5, seq=9)) == FrameTime(frame_ms=16.5, seq=9)
    assert decode_control(encode_idle(41, 512.5)) == Idle(last_seq=41, idle_ms=512.5)
    assert decode_control(encode_frame_time(0.0, seq=3, drawn=False)) == FrameTime(frame_ms=0.0, seq=3, drawn=False)
    gpu = {"name": "x", "type": "DiscreteGPU", "max_storage_binding": 1 << 30, "max_buffer_size": 1 << 31}
    assert decode_control(encode_hello(1, 0, gpu=gpu)).gpu == gpu


def test_release_messages_are_not_control():
    assert decode_control([b"pf.ring.release/1", b"\0" * 16]) is None
    assert decode_control([]) is None


@pytest.mark.parametrize("frames,match", [
    ([CONTROL_TAG], "2 frames"),
    ([CONTROL_TAG, b"{not json"], "not JSON"),
    ([CONTROL_TAG, b"[1]"], "JSON object"),
    ([CONTROL_TAG, json.dumps({"type": "nope"}).encode()], "unknown type 'nope'"),
    ([CONTROL_TAG, json.dumps({"type": "hello"}).encode()], "'hello': missing or bad field"),
    ([CONTROL_TAG, json.dumps({"type": "hello", "pid": 1, "gpu": 5}).encode()], "gpu must be an object"),
    ([CONTROL_TAG, json.dumps({"type": "frame", "frame_ms": "x"}).encode()], "'frame': missing or bad"),
    ([CONTROL_TAG, json.dumps({"type": "frame", "frame_ms": -1}).encode()], "frame_ms must be finite"),
    ([CONTROL_TAG, json.dumps({"type": "idle"}).encode()], "'idle': missing or bad"),
])
def test_malformed(frames, match):
    with pytest.raises(ControlMessageError, match=match):
        decode_control(frames)
