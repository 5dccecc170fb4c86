"""The rosbridge transport against a rosbridge v2 server the test runs in its own process:
JSON (base64 data, ROS 1 names) and CBOR (byte-string data, ROS 2 names), bad messages
between good ones, the server killed and restarted mid-stream, unsubscribe on stop."""
import json
import os
import time

import numpy as np
import pytest

from pointflow.config import ConfigError
from pointflow.ingest.transports import resolve_transport

from . import ros_util as ru
from .test_transports import free_port

TOPIC = "/ouster/points"


def _make(port, **opts):
    cls = resolve_transport("rosbridge")
    o = cls.validate_options({"url": f"ws://127.0.0.1:{port}", "topic": TOPIC, "reconnect_initial_s": 0.05,
                              "reconnect_max_s": 0.2, **opts}, "sources[0].options", os.getcwd())
    t = cls(o, "robot")
    t.open()
    return t


def _pull(t, it, want_chunks, want_rejected=0, timeout=30.0):
    got = []
    end = time.monotonic() + timeout
    while (len(got) < want_chunks or t.counters["rejected"] < want_rejected) and time.monotonic() < end:
        c = next(it)
        if c is not None:
            got.append(c)
    return got


@pytest.mark.parametrize("mode", ["none", "cbor"])
def test_json_and_cbor_streams_with_bad_messages_and_a_server_restart(mode):
    ros1 = mode == "none"
    pub = (lambda c: ru.publish_json(TOPIC, c)) if ros1 else (lambda c: ru.publish_cbor(TOPIC, c))
    clouds = [ru.cloud_padded(k, n=40) for k in range(3)] + [ru.cloud_organised(), ru.cloud_rgb()]
    first = [
        ("m", pub(clouds[0])),
        ("m", json.dumps({"op": "status", "level": "warning", "msg": "queue full", "id": "x"})),
        ("m", "{not json" if ros1 else b"\xff\x00garbage"),
        ("m", pub(ru.broken("truncated"))),
        ("m", ru.publish_json("/other", clouds[1], ros1) if ros1 else ru.publish_cbor("/other", clouds[1])),
        ("m", json.dumps({"op": "service_response", "service": "/x", "values": {}})),
        ("m", json.dumps({"op": "publish", "topic": TOPIC, "msg": [1, 2]})),
        ("m", pub(ru.broken("no_xyz"))),
        ("m", pub(clouds[1])),
        ("m", pub(ru.broken("field_overflow"))),
        ("m", pub(ru.broken("unknown_datatype"))),
        ("m", pub(clouds[2])),
    ]
    rest = [("m", pub(clouds[3])), ("m", json.dumps({"op": "status", "level": "error", "msg": "x"})), ("m", pub(clouds[4]))]
    port = free_port()
    typ = "sensor_msgs/PointCloud2" if ros1 else "sensor_msgs/msg/PointCloud2"
    srv = ru.RosbridgeServer(port, first)
    t = _make(port, compression=mode, type=typ, throttle_rate=100, queue_length=2)
    srv2 = None
    try:
        it = t.chunks()
        got = _pull(t, it, 3, want_rejected=8)
        c = t.counters
        assert c["rejected"] == 8, c
        assert c["rejected_truncated"] == c["rejected_no_xyz"] == c["rejected_field_overflow"] == 1
        assert c["rejected_unknown_datatype"] == c["rejected_wrong_topic"] == c["rejected_unexpected_op"] == 1
        assert c["rejected_bad_shape"] == 1 and c["rejected_" + ("bad_json" if ros1 else "bad_cbor")] == 1
        assert c["status"] == 1 and c["status_warning"] == 1
        srv.drain(2)
        sub = srv.client_messages[0]
        assert sub == {"op": "subscribe", "id": t.sub_id, "topic": TOPIC, "type": typ, "throttle_rate": 100,
                       "queue_length": 2, "compression": mode}
        srv.kill()  # the robot goes away mid-stream ...
        srv.close()
        srv2 = ru.RosbridgeServer(port, rest)  # ... and comes back
        got += _pull(t, it, 2)
        assert c["reconnects"] >= 1 and c["status_error"] == 1
        assert len(got) == 5
        for chunk, cloud in zip(got, clouds):
            pos, ch = cloud.expected()
            assert np.array_equal(chunk.positions, pos, equal_nan=True)
            assert set(chunk.channels) == set(ch)
            assert all(np.array_equal(chunk.channels[k], v) for k, v in ch.items())
            assert chunk.stamp_ns == cloud.stamp_ns and chunk.source_id == f"robot:{TOPIC}"
        t.close()
        srv2.drain(3)
        assert srv2.client_messages == [sub, {"op": "unsubscribe", "id": t.sub_id, "topic": TOPIC}]
    finally:
        t.close()
        srv.close()
        if srv2 is not None:
            srv2.close()


def test_rosbridge_feeds_source_and_ingest_processes_into_the_ring():
    clouds = [ru.cloud_padded(k, n=64) for k in range(4)]
    script = [("m", ru.publish_cbor(TOPIC, c)) for c in clouds[:2]] + [("m", ru.publish_cbor(TOPIC, ru.broken("truncated")))] \
        + [("m", ru.publish_cbor(TOPIC, c)) for c in clouds[2:]]
    port = free_port()
    srv = ru.RosbridgeServer(port, script)
    from .stage_util import base_config
    cfg = base_config()
    cfg["source"] = {"transport": "rosbridge", "options": {"url": f"ws://127.0.0.1:{port}", "topic": TOPIC,
                                                           "rename": {"reflectivity": "refl"}}}
    cfg["ring"]["extra_channels"] = ["intensity", "refl"]
    st = ru.SourceIngest(cfg)
    try:
        stats = st.wait_ingest(lambda s: s.get("chunks_accepted") == 4)
        st.wait_stats(lambda s: st.stage_stats.get("source", {}).get("transport_rejected_truncated") == 1)
        assert stats["points_out"] == 4 * 64 and stats["drops"] == {}
        snap = st.ring.snapshot()
        assert np.array_equal(snap.positions, np.concatenate([c.expected()[0] for c in clouds]).astype(np.float64))
        assert np.array_equal(snap.channels["refl"], np.concatenate([c.values["reflectivity"] for c in clouds]).astype(np.float32))
        assert np.array_equal(snap.channels["intensity"], np.concatenate([c.values["intensity"] for c in clouds]))
    finally:
        st.close()
        srv.close()


def test_rosbridge_options_are_validated():
    cls = resolve_transport("rosbridge")

    def check(opts):
        cls.validate_options({"topic": TOPIC, **opts}, "sources[0].options", os.getcwd())

    with pytest.raises(ConfigError, match=r"options\.topic.*starting with '/'"):
        cls.validate_options({}, "sources[0].options", os.getcwd())
    with pytest.raises(ConfigError, match=r"options\.type.*sensor_msgs/msg/PointCloud2, sensor_msgs/PointCloud2"):
        check({"type": "sensor_msgs/msg/Image"})
    with pytest.raises(ConfigError, match=r"options\.compression"):
        check({"compression": "png"})
    with pytest.raises(ConfigError, match=r"options\.url.*ws://"):
        check({"url": "http://robot:9090"})
    with pytest.raises(ConfigError, match=r"options\.queue_length"):
        check({"queue_length": 0})
