"""ROS 2 over rmw_zenoh across hosts (docs/ros.md, "A robot on another host"): Linux network
namespaces joined by veth pairs (netns.py), as the other link tests. The robot's publisher
(pointflow/testing/rmw_zenoh_pub.py: an rmw_zenoh session, listening on its own loopback only, as
rmw_zenoh's DEFAULT_RMW_ZENOH_SESSION_CONFIG does) reaches the viewers only through a router on
another host configured as rmw_zenohd is (``peers_failover_brokering: false``); the viewers
cannot reach the robot at all. Run as root; under CI=true they must run.

What the product guarantees here: a viewer configured as the docs' cross-host example (``mode:
peer``) gets every cloud, after one warning that says why peer mode could not work and what
to set; a ``mode: client`` viewer gets every cloud with no warning.
"""
from __future__ import annotations

import json
import pickle
import sys

import numpy as np
import pytest

pytest.importorskip("zenoh", reason="eclipse-zenoh comes with the remote extra: pip install 'pointflow[remote]'")
pytest.importorskip("rosbags", reason="rosbags comes with the ros extra: pip install 'pointflow[ros]'")

from ingest import ros_util as ru  # noqa: E402

from pointflow.testing import rmw_zenoh_pub as P  # noqa: E402

from .helpers import wait_for  # noqa: E402
from .netns import REPO, Net  # noqa: E402

PORT = 7447
TOPIC = "/ouster/points"
PUB = P.__name__  # run with -m
PROBE = str(REPO / "tests/remote/ros2_zenoh_probe.py")


def start_probe(net: Net, ns: str, zenoh: dict, name: str):
    opts = {"topic": TOPIC, "zenoh": zenoh, "max_chunks": 6, "queue_messages": 64}
    return net.spawn(ns, sys.executable, PROBE, json.dumps(opts), str(net.workdir / name), "240", log=f"{name}.log")


@pytest.mark.parametrize("mode", ["jazzy", "rolling"])
def test_a_peer_viewer_behind_the_robots_router_gets_every_cloud_and_says_why(net, mode):
    robot, rt, vp, vc = (net.host(n) for n in ("r31rob", "r31rt", "r31vp", "r31vc"))
    _, rt_robot = net.link(robot, rt)     # the router's address seen from the robot
    rt_vp, _ = net.link(rt, vp)           # ... from each viewer
    rt_vc, _ = net.link(rt, vc)
    # the router reads stdin until it closes: give it a pipe that stays open while it runs
    net.spawn(rt, "sh", "-c", f"sleep infinity | {sys.executable} -m {PUB} --router tcp/0.0.0.0:{PORT}", log="router.log")
    wait_for(lambda: "READY" in net.log("router.log"), 60, "the router", lambda: net.log("router.log"))
    clouds = [ru.cloud_padded(k, n=50 + k) for k in range(6)]
    spec = {"connect": f"tcp/{rt_robot}:{PORT}", "mode": mode, "advertise": [(TOPIC, P.PC2)],
            "script": [("put", TOPIC, P.cdr_cloud(c)) for c in clouds], "min_subscribers": 2,
            "go_at_once": True, "linger_s": 300}
    (net.workdir / "spec.pickle").write_bytes(pickle.dumps(spec))
    net.spawn(robot, sys.executable, "-m", PUB, str(net.workdir / "spec.pickle"), log="robot.log")
    wait_for(lambda: "READY" in net.log("robot.log"), 60, "the robot's publisher", lambda: net.log("robot.log"))
    # the docs' cross-host example, as written, and the client it turns into
    peer = start_probe(net, vp, {"mode": "peer", "connect": [f"tcp/{rt_vp}:{PORT}"], "insecure": True}, "peer")
    client = start_probe(net, vc, {"mode": "client", "connect": [f"tcp/{rt_vc}:{PORT}"], "insecure": True}, "client")
    for name, p in (("peer", peer), ("client", client)):
        try:
            assert p.wait(240) == 0, net.log(f"{name}.log")
        except Exception:
            raise AssertionError(f"{name}: {net.log(f'{name}.log')}\nrobot: {net.log('robot.log')}") from None
    assert f"SENT {TOPIC} 6" in net.log("robot.log"), net.log("robot.log")
    want = np.concatenate([c.expected()[0] for c in clouds]).astype(np.float64)
    for name in ("peer", "client"):
        log = net.log(f"{name}.log")
        c = json.loads((net.workdir / f"{name}.json").read_text())
        assert "probe: done, 6 clouds" in log and "Traceback" not in log, log
        assert c["messages"] == 6 and c["points"] == len(want) and c["lost_in_transit_messages"] == 0, c
        assert np.array_equal(np.load(net.workdir / f"{name}.npy"), want)
        if mode == "rolling":  # served on _buf_cpu, as a CPU-only buffer-aware subscription
            assert c["buffer_cpu_messages"] == 6, c
    # peer mode cannot work behind rmw_zenohd: said once, with the remedy, and then it works
    peer_log = net.log("peer.log")
    assert peer_log.count("reopened as a client of the router") == 1, peer_log
    assert "peers_failover_brokering: false" in peer_log and "zenoh.mode: client" in peer_log
    assert "no PointCloud2 topic is published" not in peer_log, peer_log
    assert json.loads((net.workdir / "peer.json").read_text())["peer_reopened_as_client"] == 1
    assert "reopened" not in net.log("client.log")
    assert "peer_reopened_as_client" not in json.loads((net.workdir / "client.json").read_text())
