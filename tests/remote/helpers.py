"""Configs and waits shared by the link tests.

What the link guarantees on a loaded machine (load 17-32 on 2 cores), and so what these
tests assert: every point the sender put on the link is received or counted lost in
transit, and the receiver's own accounting balances; neither the counts nor their
exactness depend on load. Load changes how long things take, and one more thing: a peer
starved of CPU for longer than ``heartbeat_timeout_s`` looks dead to ZeroMQ's heartbeat,
which drops the connection (what was in flight is counted lost) and reconnects. So the
links here use the product's default timeout (3 s) unless a test is about a dead link, and
every wait is long enough for a loaded machine (nothing is timed)."""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from .netns import REPO, Net, read_stats, stop

PORT = 47311


def write_cfg(path: Path, cfg: dict) -> str:
    path.write_text(json.dumps(cfg))  # JSON is YAML
    return str(path)


def synthetic_source(name: str = "lidar", scans: int = 6, points: int = 4000, hz: float = 10.0) -> dict:
    return {"transport": "synthetic", "name": name,
            "options": {"points_per_scan": points, "scans": scans, "scan_hz": hz, "chunks_per_scan": 4,
                        "moving_objects": 0, "seed": 1}}


def sender_cfg(source: dict | list, **send) -> dict:
    sources = source if isinstance(source, list) else [source]
    return {"sources": sources, "send": {"socket": "push", "bind": False, "queue_chunks": 256,
                                         "heartbeat_ivl_s": 0.3, "heartbeat_timeout_s": 3.0,
                                         "heartbeat_ttl_s": 3.0, "reconnect_max_s": 0.5, **send}}


def receiver_cfg(endpoint: str, socket: str = "pull", bind: bool = True, **opts) -> dict:
    return {"source": {"transport": "zmq", "name": "link",
                       "options": {"endpoint": endpoint, "socket": socket, "bind": bind,
                                   "heartbeat_ivl_s": 0.3, "heartbeat_timeout_s": 3.0, "heartbeat_ttl_s": 3.0,
                                   "reconnect_max_s": 0.5, **opts}},
            "ring": {"max_points": 300_000},
            "cadence": {"target_hz": 10},
            "render": {"backend": "cpu", "size": [64, 48], "output": {"dir": None}},
            "tracing": {"enabled": False},
            "supervisor": {"max_restarts": 0}}


def start_receiver(net: Net, ns: str, cfg: dict, name: str = "recv"):
    path = write_cfg(net.workdir / f"{name}.yaml", cfg)
    # stopped by the test (finish); the duration only bounds a test that never gets there
    return net.pointflow(ns, "run", path, "--duration", "600", "--out", str(net.workdir / name), "-q",
                         log=f"{name}.log")


def start_sender(net: Net, ns: str, cfg: dict, name: str = "send"):
    path = write_cfg(net.workdir / f"{name}.yaml", cfg)
    return net.pointflow(ns, "send", path, "--out", str(net.workdir / name), "-q", log=f"{name}.log")


def start_probe(net: Net, ns: str, opts: dict, senders: int = 1, name: str = "probe", timeout: float = 150):
    return net.spawn(ns, sys.executable, str(REPO / "tests/remote/probe.py"), json.dumps(opts),
                     str(net.workdir / name), str(senders), str(timeout), log=f"{name}.log")


def wait_for(pred, timeout: float, what: str, logs=lambda: "") -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return
        time.sleep(0.1)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}\n{logs()}")


def wait_listening(net: Net, log: str, timeout: float = 120) -> None:
    """A receiver is up once its link source logged it (the zmq transport opened)."""
    wait_for(lambda: "probe: listening" in net.log(log) or "ring " in net.log(log), timeout,
             f"{log} to start", lambda: net.log(log))


def finish(net: Net, sender, receiver, senders_ended: int = 1, name: str = "recv", sender_name: str = "send",
           timeout: float = 180) -> tuple[dict, dict]:
    """Wait for the sender to end and the receiver to log its final sync; stop the receiver;
    return (sender stats, receiver stats)."""
    assert sender.wait(timeout) == 0, net.log(f"{sender_name}.log")
    wait_for(lambda: net.log(f"{name}.log").count("stopped: sent") >= senders_ended, 90,
             "the sender's final sync at the receiver", lambda: net.log(f"{name}.log"))
    assert stop(receiver, 90) == 0, net.log(f"{name}.log")  # three waves of stops, each up to 5 s, then exits
    return read_stats(net.workdir / sender_name / "stats.json"), read_stats(net.workdir / name / "stats.json")


def assert_exact(snd: dict, rcv: dict, lost_ok: bool = False) -> None:
    """Every point the sender put on the link is received or counted lost in transit, and
    the receiving pipeline's own accounting balances: what its link source received is
    forwarded to ingest or counted dropped there (its send queue full on a busy machine)."""
    sa, ra = snd["accounting"], rcv["accounting"]
    assert sa["sender_balanced"] and sa["lost_before_sender"] == 0, sa
    assert sa["link_sent"] > 0
    assert ra["link_sent"] == sa["sender_received"], (sa, ra)
    assert ra["link_received"] + ra["lost_in_transit"] == sa["sender_received"], (sa, ra)
    assert ra["link_balanced"] and ra["ingest_balanced"] and ra["ring_agrees"], ra
    assert ra["sources_received"] == ra["link_received"] and ra["sources_balanced"], ra
    assert ra["lost_before_ingest"] == 0 and ra["ingest_received"] == ra["sources_forwarded"], ra
    assert ra["link_received"] == ra["ingest_received"] + ra["sources_dropped"], ra
    if not lost_ok:
        assert ra["lost_in_transit"] == 0, ra


def positions_of_file(path: Path) -> np.ndarray:
    with np.load(path) as z:
        return z["xyz"]
