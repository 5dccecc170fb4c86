"""rosbridge with frames on: the transport also subscribes to /tf and /tf_static and the
clouds land in the fixed frame (real server process, real source and ingest processes)."""
import json

import numpy as np

from ingest import ros_util as ru
from ingest.stage_util import base_config
from ingest.test_transports import free_port
from . import truth as T

TOPIC = "/ouster/points"
EXT = T.extrinsic([0.9, 0.0, 1.7], [0, 2, 30])


def _tf(topic, items):
    """ROS 1 names (secs/nsecs) as rosbridge sends them."""
    ts = [{"header": {"stamp": {"secs": st // T.SEC, "nsecs": st % T.SEC}, "frame_id": "/" + parent},
           "child_frame_id": child,
           "transform": {"translation": dict(zip("xyz", map(float, tr))), "rotation": dict(zip("xyzw", map(float, q)))}}
          for parent, child, st, tr, q in items]
    return json.dumps({"op": "publish", "topic": topic, "msg": {"transforms": ts}})


def test_rosbridge_subscribes_to_tf_and_places_the_clouds():
    robot = T.Robot(n_tf=81)
    clouds = [ru.cloud_padded(k, n=40) for k in range(4)]
    script = [("m", _tf("/tf_static", [("base_link", "lidar", 0, EXT[1], T.matrix_to_quat(EXT[0]))]))]
    tfs = robot.tf()
    for k, (st, R, p) in enumerate(tfs):
        script.append(("m", _tf("/tf", [("odom", "base_link", st, p, T.matrix_to_quat(R))])))
        if k == 62:  # the last cloud arrives before the /tf samples that bracket it: it waits
            script.append(("m", ru.publish_json(TOPIC, clouds[3])))

    script += [("m", ru.publish_json(TOPIC, c)) for c in clouds[:3]]
    port = free_port()
    cfg = base_config()
    cfg["ring"]["extra_channels"] = ["intensity"]
    cfg["source"] = {"transport": "rosbridge", "options": {"url": f"ws://127.0.0.1:{port}", "topic": TOPIC,
                                                           "compression": "none", "type": "sensor_msgs/PointCloud2",
                                                           "reconnect_initial_s": 0.05, "reconnect_max_s": 0.2}}
    cfg["frames"] = {"fixed": "odom", "tf_wait_ms": 5000}
    st = ru.SourceIngest(cfg)
    srv = None
    try:
        # the server starts once ingest is up: a live source drops what ingest cannot take yet
        st.wait_ingest(lambda s: "points_in" in s and "source" in st.stage_stats)
        srv = ru.RosbridgeServer(port, script)
        stats = st.wait_ingest(lambda s: s["points_out"] == 160, timeout=120)
        snap = st.ring.snapshot()
        srv.drain(1.0)
    finally:
        st.close()
        if srv is not None:
            srv.close()
    subs = {m["topic"]: m["type"] for m in srv.client_messages if m.get("op") == "subscribe"}
    assert {"/tf", "/tf_static"} <= set(subs) and subs["/tf"] == "tf2_msgs/TFMessage"
    want = {}
    for c in [clouds[3]] + clouds[:3]:
        pos = c.values["x"], c.values["y"], c.values["z"]
        pts = np.column_stack(pos).astype(np.float64)
        want[c.stamp_ns] = T.to_fixed(robot, EXT, pts, c.stamp_ns + c.values["t"].astype(np.int64))
    got = snap.positions
    exp = np.concatenate([want[c.stamp_ns] for c in [clouds[3]] + clouds[:3]])
    assert np.abs(got - exp).max() < 5e-5, np.abs(got - exp).max()
    assert stats["drops"] == {} and stats["frames"]["sources"]["source:" + TOPIC]["deskew"].startswith("Ouster t")
