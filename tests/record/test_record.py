"""A real pipeline records what ingest accepted; an independent reader (the ``mcap``
library + ``mcap-ros2-support``) finds every point, channel value and stamp."""
from __future__ import annotations

import time

import numpy as np
import pytest
import zmq

from pointflow import wire
from pointflow.chunk import PointChunk, new_trace_id
from pointflow.config import ConfigError, load_config
from pointflow.runtime.pipeline import Pipeline

from .helpers import free_tcp_port, read_recording, summary_intact


def _chunk(src: str, seq: int, n: int, rng, stamp_ns: int, nan_rows=()):
    pos = rng.normal(size=(n, 3)) * 50 + [6.4e5, 4.9e6, 12.0]  # georeferenced: float64 matters
    pos[list(nan_rows), 1] = np.nan
    return PointChunk(positions=pos, source_id=src, seq=seq, trace_id=new_trace_id(), t_sent_ns=time.monotonic_ns(),
                      stamp_ns=stamp_ns, channels={
                          "intensity": rng.random(n, dtype=np.float32) * 255,
                          "rgb": rng.integers(0, 256, size=(n, 3), dtype=np.uint8),
                          "classification": rng.integers(0, 20, size=n).astype(np.float32),
                          "unrecorded": np.ones(n, np.float32)})


def test_recording_holds_every_accepted_point(tmp_path):
    port = free_tcp_port()
    rec = tmp_path / "rec" / "run.mcap"
    cfg = {
        "sources": [{"transport": "zmq", "name": "remote", "external": True}],
        "endpoints": {"ingest": f"tcp://127.0.0.1:{port}"},
        "ring": {"max_points": 200_000},
        "render": {"backend": "cpu", "size": [64, 48], "output": {"every_n_frames": 1000}},
        "record": {"path": str(rec), "channels": ["intensity", "rgb", "classification"], "chunk_size": 100_000},
        "supervisor": {"max_restarts": 0, "hung_after_ms": 10_000},  # starved on a loaded machine is not hung
    }
    rng = np.random.default_rng(7)
    sent: dict[str, list[PointChunk]] = {"lidar_a": [], "lidar/b": []}
    zctx = zmq.Context()
    push = zctx.socket(zmq.PUSH)
    push.setsockopt(zmq.LINGER, 2000)
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path / "out")) as pipe:
        pipe.wait(30, until=lambda: pipe.stats()["stages"]["recorder"].get("pid") and
                  pipe.stats()["stages"]["ingest"].get("messages_in", -1) >= 0 and
                  pipe.stats()["stages"]["recorder"].get("record_files", -1) >= 0)
        push.connect(f"tcp://127.0.0.1:{port}")
        t_before = time.time_ns()
        for i in range(12):
            for src in sent:
                stamp = 0 if i == 5 else 1_700_000_000_000_000_000 + i * 100_000_000 + (src == "lidar/b")
                c = _chunk(src, i, 700 + 13 * i, rng, stamp, nan_rows=(3, 9) if i == 2 else ())
                sent[src].append(c)
                wire.send(push, c)
        total = sum(c.n for cs in sent.values() for c in cs)
        pipe.wait(30, until=lambda: pipe.stats()["stages"]["ingest"]["points_in"] >= total)
        t_after = time.time_ns()
    push.close()
    zctx.term()
    st = pipe.stats()
    acc = st["accounting"]
    ing = st["stages"]["ingest"]
    assert ing["points_in"] == total and ing["drops"] == {"non_finite": 4}
    assert acc["ingest_balanced"] and acc["ring_agrees"]
    assert acc["record_offered"] == ing["points_out"] == total - 4
    assert acc["record_covers_ring"] and acc["record_tap_balanced"] and acc["recorder_balanced"]
    assert acc["record_dropped"] == 0 and acc["recorder_dropped"] == 0 and acc["lost_before_recorder"] == 0
    assert acc["recorder_written"] == ing["points_out"]
    assert st["stages"]["recorder"]["record_bytes"] == rec.stat().st_size

    assert summary_intact(str(rec))
    msgs = read_recording(str(rec))
    by_topic: dict[str, list] = {}
    for m in msgs:
        by_topic.setdefault(m.topic, []).append(m)
    assert sorted(by_topic) == ["/pointflow/lidar/b", "/pointflow/lidar_a"]
    for src, topic in (("lidar_a", "/pointflow/lidar_a"), ("lidar/b", "/pointflow/lidar/b")):
        got = by_topic[topic]
        assert [m.sequence for m in got] == list(range(12)), "one message per chunk, in order"
        assert sum(m.n for m in got) == sum(c.n for c in sent[src]) - 2  # chunk 2's NaN rows
        for m, c in zip(got, sent[src]):
            keep = np.isfinite(c.positions).all(axis=1)
            np.testing.assert_array_equal(m.positions, c.positions[keep])  # float64, bit for bit
            assert sorted(m.channels) == ["classification", "intensity", "rgb"]
            for k in ("intensity", "rgb", "classification"):
                np.testing.assert_array_equal(m.channels[k], c.channels[k][keep])
            assert m.frame_id == "map"
            if c.stamp_ns:
                assert m.stamp_ns == c.stamp_ns == m.publish_time
            else:  # no capture time: ingest's wall clock when it took the chunk
                assert t_before <= m.stamp_ns <= t_after
    logs = [m.log_time for m in msgs]
    assert logs == sorted(logs), "log times never go back"


def test_record_config_errors_name_the_key():
    base = {"source": {"transport": "synthetic"}}
    for rec, key in (({"compression": "gzip"}, "record.compression"),
                     ({"topic": "no slash"}, "record.topic"),
                     ({"split": {"size_mb": -1}}, "record.split.size_mb"),
                     ({"chunk_size": 0}, "record.chunk_size"),
                     ({"channels": ["x"]}, "record.channels[0]")):
        with pytest.raises(ConfigError, match=key.replace("[", r"\[").replace("]", r"\]")):
            load_config({**base, "record": rec})
    cfg = load_config({**base, "record": {"path": "a.mcap", "channels": ["beam"]}})
    assert "beam" in cfg.ring_channels(), "a recorded channel is kept by ingest"
