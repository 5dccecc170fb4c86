"""With ``frames.fixed`` the recording is in the fixed frame and carries the transforms:
/tf (as they arrived) and /tf_static (first in every split file), read back with the ``mcap``
library and the ``mcap-ros2-support`` decoder; and the rosbag transport replays it."""
from __future__ import annotations

import pytest

from pointflow.runtime.pipeline import Pipeline

from .helpers import summary_intact

FIXED = "odom"
HEIGHT = 1.8  # the synthetic source's sensor_height: base_link -> lidar


def _moving(rec: str, **record) -> dict:
    return {"source": {"transport": "synthetic",
                       "options": {"mode": "moving", "scan_hz": 10, "points_per_scan": 4000, "chunks_per_scan": 4,
                                   "scans": 8, "realtime": False, "drive_speed": 8}},
            "frames": {"fixed": FIXED, "tf_wait_ms": 500},
            "ring": {"max_points": 100_000},
            "render": {"backend": "cpu", "size": [64, 48], "output": {"every_n_frames": 1000}},
            "supervisor": {"max_restarts": 0, "hung_after_ms": 10_000},
            "record": {"path": rec, "chunk_size": 30_000, "queue_messages": 1024, **record}}


def _run(cfg: dict, out) -> dict:
    with Pipeline.from_dict(cfg, out_dir=str(out)) as pipe:
        st = lambda: pipe.stats()["stages"]
        done = lambda: st()["source"]["finished"] and st()["ingest"]["points_in"] >= st()["source"]["points_out"] > 0
        pipe.wait(90, until=done)
        assert done()
    return pipe.stats()


def _read(path) -> list[tuple[str, str, object]]:
    """(topic, schema name, decoded message) in log-time order, pointflow's code not involved."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out = []
    with open(path, "rb") as f:
        for schema, channel, _msg, ros in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                log_time_order=True):
            out.append((channel.topic, schema.name, ros))
    return out


def _stamp(h) -> int:
    return h.stamp.sec * 1_000_000_000 + h.stamp.nanosec


def test_recording_in_the_fixed_frame_with_transforms(tmp_path):
    rec = tmp_path / "m.mcap"
    st = _run(_moving(str(rec), split={"size_mb": 0.12}), tmp_path / "o1")
    files = [rec, *sorted(tmp_path.glob("m.0*.mcap"))]
    assert len(files) >= 3, "split by size into several files"
    ing = st["stages"]["ingest"]
    assert ing["frames"]["fixed"] == FIXED and ing["frames"]["transforms_in"] > 0
    assert ing["record_transforms_sent"] > 0 and ing["record_transforms_dropped"] == 0

    points = 0
    tf_stamps = []
    for p in files:
        assert summary_intact(str(p)), p
        msgs = _read(p)
        topics = {t for t, _, _ in msgs}
        assert topics >= {"/tf_static"}, f"{p.name} has no /tf_static"
        # each file stands alone: the static transforms come first in it
        topic, schema, first = msgs[0]
        assert (topic, schema) == ("/tf_static", "tf2_msgs/msg/TFMessage")
        (mount,) = first.transforms
        assert (mount.header.frame_id, mount.child_frame_id) == ("base_link", "lidar")
        assert (mount.transform.translation.x, mount.transform.translation.y,
                mount.transform.translation.z) == (0.0, 0.0, HEIGHT)
        assert mount.transform.rotation.w == 1.0
        assert [t for t, _, _ in msgs].count("/tf_static") == 1, "the static set changes never: written once per file"
        for topic, schema, m in msgs:
            if schema == "sensor_msgs/msg/PointCloud2":
                assert m.header.frame_id == FIXED, "clouds are recorded in the fixed frame"
                points += m.width * m.height
            elif topic == "/tf":
                assert schema == "tf2_msgs/msg/TFMessage"
                for ts in m.transforms:
                    assert (ts.header.frame_id, ts.child_frame_id) == (FIXED, "base_link")
                    tf_stamps.append(_stamp(ts.header))
    assert points == ing["points_out"] == st["stages"]["recorder"]["points_out"]
    assert len(tf_stamps) == ing["record_transforms_sent"] - 1  # all but the static mount
    assert len(tf_stamps) >= 8 * 2, "20 Hz odom -> base_link over 8 scans at 10 Hz"
    assert all(b > a for a, b in zip(tf_stamps, tf_stamps[1:])), "/tf stamps increase, each sample once"
    assert st["stages"]["recorder"]["record_transforms"] == len(tf_stamps)

    # replay: the rosbag transport reads the clouds and /tf, /tf_static back; fixed frame the same
    replay = {"source": {"transport": "rosbag", "options": {"path": str(tmp_path / "m*.mcap"), "rate": 0}},
              "frames": {"fixed": FIXED, "tf_wait_ms": 500},
              "ring": {"max_points": 100_000},
              "render": {"backend": "cpu", "size": [64, 48], "output": {"every_n_frames": 1000}},
              "supervisor": {"max_restarts": 0, "hung_after_ms": 10_000}}
    st2 = _run(replay, tmp_path / "o2")
    ing2 = st2["stages"]["ingest"]
    assert ing2["points_out"] == points and not ing2.get("drops", {}).get("no_transform")
    fr = ing2["frames"]
    assert fr["transforms_in"] >= len(tf_stamps) + 1 and not fr["transforms_rejected"]
    (src,) = fr["sources"].values()
    assert src["frame"] == FIXED


def test_no_transforms_without_frames(tmp_path):
    """frames.fixed null: the recording holds the clouds only, in the sensor's frame."""
    rec = tmp_path / "n.mcap"
    cfg = _moving(str(rec))
    cfg["source"]["options"]["scans"] = 2
    del cfg["frames"]
    st = _run(cfg, tmp_path / "o")
    msgs = _read(rec)
    assert {t for t, _, _ in msgs} == {"/pointflow/synthetic"} or all(s.endswith("PointCloud2") for _, s, _ in msgs)
    assert {m.header.frame_id for _, _, m in msgs} == {"lidar"}
    assert "record_transforms_sent" not in st["stages"]["ingest"]


if __name__ == "__main__":  # pragma: no cover
    pytest.main([__file__, "-q"])


def test_restarted_recorder_file_starts_with_the_static_transforms(tmp_path):
    """ingest sends the static mount once; a recorder killed and restarted still starts its
    new file with it (read from the file before)."""
    import os
    import signal

    rec = tmp_path / "k.mcap"
    cfg = _moving(str(rec), flush_s=0.2)
    cfg["source"]["options"].update(scans=0, realtime=True)
    cfg["supervisor"] = {"max_restarts": 2, "restart_backoff_ms": 100, "hung_after_ms": 10_000}
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path / "out")) as pipe:
        recorder = lambda: pipe.stats()["stages"]["recorder"]
        pipe.wait(60, until=lambda: recorder().get("record_messages", 0) >= 20)
        before = recorder()["record_messages"]
        os.kill(recorder()["pid"], signal.SIGKILL)
        pipe.wait(60, until=lambda: recorder()["restarts"] == 1 and recorder().get("record_messages", 0) >= before + 10)
        assert recorder()["restarts"] == 1
    msgs = _read(tmp_path / "k.0001.mcap")
    topic, _, first = msgs[0]
    assert topic == "/tf_static"
    assert [(t.header.frame_id, t.child_frame_id, t.transform.translation.z) for t in first.transforms] == \
        [("base_link", "lidar", HEIGHT)]
    assert any(t == "/tf" for t, _, _ in msgs[1:])
    assert {m.header.frame_id for _, s, m in msgs if s.endswith("PointCloud2")} == {FIXED}


def _tf(parent, child, stamp, z, static):
    from pointflow.frames.message import Transform

    return Transform(parent, child, stamp, (0.0, 0.0, z), (0.0, 0.0, 0.0, 1.0), static)


def test_static_set_rewritten_when_it_changes_and_tap_never_waits(tmp_path):
    """Recorder: an unchanged static is not written again, a changed one rewrites the whole
    set; the tap drops transforms it cannot send at once and counts them apart from points."""
    import logging

    import numpy as np
    import zmq

    from pointflow.chunk import PointChunk
    from pointflow.frames.message import Transforms
    from pointflow.record.config import RecordConfig
    from pointflow.record.process import Recorder
    from pointflow.record.tap import RecordTap
    from pointflow.stage.context import StageCounters

    path = tmp_path / "u.mcap"
    rec = Recorder(RecordConfig(path=str(path)), StageCounters(), logging.getLogger("t"))
    rec.add_transforms(Transforms([_tf("base_link", "lidar", 0, 1.0, True)]))
    rec.add(PointChunk(positions=np.zeros((10, 3), np.float32), seq=0, source_id="s", frame_id=FIXED))
    rec.add_transforms(Transforms([_tf("base_link", "lidar", 0, 1.0, True), _tf(FIXED, "base_link", 5, 0.0, False)]))
    rec.add_transforms(Transforms([_tf("base_link", "imu", 0, 2.0, True)]))
    rec.close()
    msgs = _read(path)
    assert [t for t, _, _ in msgs] == ["/tf_static", "/pointflow/s", "/tf", "/tf_static"]
    assert [(t.child_frame_id, t.transform.translation.z) for t in msgs[-1][2].transforms] == \
        [("lidar", 1.0), ("imu", 2.0)], "the whole static set, with the new one"

    zctx = zmq.Context()
    pull = zctx.socket(zmq.PULL)
    pull.setsockopt(zmq.RCVHWM, 1)
    pull.bind(f"ipc://{tmp_path}/tf.sock")
    tap = RecordTap(zctx, f"ipc://{tmp_path}/tf.sock", hwm=1)
    try:
        for i in range(200):
            tap.offer_transforms(Transforms([_tf(FIXED, "base_link", i, 0.0, False)] * 3))
        s = tap.stats()
        assert s["record_transforms_sent"] + s["record_transforms_dropped"] == 600
        assert s["record_transforms_dropped"] > 0 and s["record_dropped"] == 0 == s["record_offered"]
    finally:
        tap.sock.setsockopt(zmq.LINGER, 0)
        tap.close()
        pull.close(0)
        zctx.term()
