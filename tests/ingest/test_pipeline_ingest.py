"""Transports and ingest inside a full supervised pipeline (all stages real processes)."""
import time

import numpy as np
import zmq

from pointflow import Pipeline, wire
from pointflow.chunk import PointChunk

from .test_transports import free_port


def _cfg(source):
    return {"source": source, "ring": {"max_points": 200_000},
            "render": {"backend": "cpu", "size": [160, 120], "output": {"dir": None}}}


def test_counts_agree_across_the_source_ingest_link_after_stop(tmp_path):
    src = {"transport": "synthetic", "options": {"points_per_scan": 20_000, "scan_hz": 10}}
    with Pipeline.from_dict(_cfg(src), out_dir=str(tmp_path)) as p:
        p.wait(30, until=lambda: p.stats()["stages"].get("ingest", {}).get("points_out", 0) > 50_000)
    st = p.stats()["stages"]
    s, i = st["source"], st["ingest"]
    assert s["points_out"] > 50_000
    assert i["points_in"] == s["points_out"]  # nothing lost in flight at shutdown
    assert i["points_in"] == i["points_out"] + sum(i["drops"].values())
    assert i["rejected_messages"] == 0


def test_zmq_transport_feeds_a_pipeline(tmp_path):
    port = free_port()
    z = zmq.Context()
    peer = z.socket(zmq.PUSH)
    peer.bind(f"tcp://127.0.0.1:{port}")
    try:
        src = {"transport": "zmq", "options": {"endpoint": f"tcp://127.0.0.1:{port}", "socket": "pull"}}
        with Pipeline.from_dict(_cfg(src), out_dir=str(tmp_path)) as p:
            rng = np.random.default_rng(0)
            for k in range(20):
                wire.send(peer, PointChunk(positions=rng.uniform(-5, 5, (1000, 3)),
                                           channels={"intensity": np.full(1000, k, np.float32)}))
            peer.send(b"garbage")
            # the source reports its rejection in its own heartbeat, maybe after ingest's
            p.wait(60, until=lambda: p.stats()["stages"].get("ingest", {}).get("points_out", 0) >= 20_000
                   and p.stats()["stages"].get("source", {}).get("transport_rejected", 0) >= 1)
            st = p.stats()["stages"]
        assert st["ingest"]["points_out"] == 20_000
        assert st["source"]["transport_rejected"] == 1
    finally:
        peer.close(linger=0)
        z.term()
