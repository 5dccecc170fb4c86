"""The recording's parts without a pipeline: ingest never waits for the recorder (its copies
are dropped and counted instead), the progress line and ``pointflow inspect``."""
from __future__ import annotations

import os

import numpy as np
import pytest
import zmq

from pointflow import cli
from pointflow.chunk import PointChunk
from pointflow.ingest.process import Ingestor
from pointflow.profiling.report import live_summary
from pointflow.record.config import RecordConfig, topic_for
from pointflow.record.process import Recorder
from pointflow.record.tap import RecordTap
from pointflow.ring import PointRing
from pointflow.stage.context import StageCounters

from .helpers import read_recording


@pytest.fixture
def ring():
    r = PointRing(100_000, channels=["intensity"])
    yield r
    r.close()
    r.unlink()


def _c(n, seq, src="s"):
    return PointChunk(positions=np.random.default_rng(seq).normal(size=(n, 3)), seq=seq, source_id=src,
                      channels={"intensity": np.full(n, seq, np.float32)})


def test_ingest_drops_the_recordings_copy_instead_of_waiting(ring, tmp_path):
    """A recorder that does not read (a slow disk): past the high-water mark ingest drops its
    copies for the recording, counts them, and the ring still gets every point."""
    zctx = zmq.Context()
    ep = f"ipc://{tmp_path}/rec.sock"
    pull = zctx.socket(zmq.PULL)
    pull.setsockopt(zmq.RCVHWM, 2)
    pull.bind(ep)
    tap = RecordTap(zctx, ep, hwm=2)
    try:
        ing = Ingestor(ring, record=tap)
        for i in range(200):
            ing.add_chunk(_c(500, i))
            ing.flush()
        s = ing.stats_extra()
        assert ing.counters.points_out == 200 * 500, "the ring is not held back by the recording"
        assert s["record_offered"] == 200 * 500 == s["record_sent"] + s["record_dropped"]
        assert s["record_dropped"] > 0 and s["record_sent"] > 0
    finally:
        tap.sock.setsockopt(zmq.LINGER, 0)
        tap.close()
        pull.close(0)
        zctx.term()


def test_inspect_lists_topics_counts_and_time(tmp_path, capsys):
    rc = RecordConfig(path=str(tmp_path / "x.mcap"))
    log = __import__("logging").getLogger("t")
    counters = StageCounters()
    rec = Recorder(rc, counters, log)
    for i in range(5):
        rec.add(_c(100 + i, i, "front"))
        rec.add(_c(10, i, "rear"))
    rec.close()
    assert counters.points_out == 5 * 10 + sum(100 + i for i in range(5))
    assert cli.main(["inspect", rc.path]) == 0
    out = capsys.readouterr().out
    assert "10 messages, 560 points" in out and "summary: intact" in out
    assert "/pointflow/front  sensor_msgs/msg/PointCloud2  5 messages  510 points" in out
    assert "/pointflow/rear  sensor_msgs/msg/PointCloud2  5 messages  50 points" in out
    assert [m.topic for m in read_recording(rc.path)][:2] == ["/pointflow/front", "/pointflow/rear"]
    (tmp_path / "not.mcap").write_text("hello")
    assert cli.main(["inspect", str(tmp_path / "not.mcap")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot read as MCAP" in err
    # a recording cut short: the rosbag source refuses it and names the way to a copy that replays
    from pointflow.ingest.transports.rosbag import _open_reader

    cut, fixed = tmp_path / "cut.mcap", tmp_path / "fixed.mcap"
    data = open(rc.path, "rb").read()
    cut.write_bytes(data[:-30])  # its footer and end magic gone, every message still there
    with pytest.raises(ValueError, match=rf"{cut}: cannot read.*`pointflow inspect {cut} --recover OUT\.mcap`"):
        _open_reader(str(cut))
    assert cli.main(["inspect", str(cut), "--recover", str(fixed)]) == 0
    r = _open_reader(str(fixed))
    assert r.message_count == 10
    r.close()
    # recovered in place: the recording is replaced by its whole copy (it was emptied first)
    capsys.readouterr()
    assert cli.main(["inspect", str(cut), "--recover", str(cut)]) == 0
    r = _open_reader(str(cut))
    assert r.message_count == 10
    r.close()
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".recover-")], "no temporary copy left"
    # a folder, or an output with nowhere to go: one line each, no traceback
    capsys.readouterr()
    assert cli.main(["inspect", str(tmp_path)]) == 1
    assert cli.main(["inspect", str(cut), "--recover", str(tmp_path / "nodir" / "x.mcap")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 2 and "a folder; inspect reads one MCAP file" in err and "no folder" in err, err
    assert "Traceback" not in err


def test_topic_names_are_valid_ros_names():
    assert topic_for("/pointflow", "lidar") == "/pointflow/lidar"
    assert topic_for("/pointflow", "rosbag:/os/points") == "/pointflow/rosbag/os/points"
    assert topic_for("/pf/", "front lidar-2") == "/pf/front_lidar_2"
    assert topic_for("/", "9x") == "/_9x"


def test_progress_line_shows_the_recording():
    stats = {"stages": {"recorder": {"record_bytes": 12_300_000, "record_messages": 40, "record_error": "disk_full"}},
             "accounting": {"record_dropped": 5, "recorder_dropped": 1000}}
    line = live_summary(stats)
    assert "rec=12.3MB/40msg" in line and "missed=1.0k" in line and "STOPPED:disk_full" in line


def test_a_chunk_the_encoder_cannot_take_is_counted_and_the_recording_goes_on(tmp_path):
    counters = StageCounters()
    rec = Recorder(RecordConfig(path=str(tmp_path / "e.mcap")), counters, __import__("logging").getLogger("t"))
    rec.add(PointChunk(positions=np.zeros((3, 3)), channels={"bad": np.zeros((3, 2, 2))}, seq=0))  # 3-D channel
    rec.add(_c(4, 1))
    rec.close()
    assert counters.points_in == 7 and counters.points_out == 4 and counters.drops == {"encode_error": 3}
    assert [m.sequence for m in read_recording(str(tmp_path / "e.mcap"))] == [1]


def test_run_with_record_flag_starts_the_recorder(tmp_path, capsys):
    import json

    import yaml

    cfg = tmp_path / "p.yaml"
    cfg.write_text(yaml.safe_dump({"source": {"transport": "synthetic", "options": {"points_per_scan": 5000}},
                                   "ring": {"max_points": 50_000}, "render": {"backend": "cpu", "size": [64, 48]},
                                   "supervisor": {"hung_after_ms": 10_000}}))
    rec = tmp_path / "r" / "x.mcap"
    assert cli.main(["run", str(cfg), "--duration", "3", "-q", "--out", str(tmp_path / "out"),
                     "--record", str(rec)]) == 0
    out = capsys.readouterr().out
    assert "recorded " in out and str(rec) in out or "to -" in out
    st = json.loads((tmp_path / "out" / "stats.json").read_text())
    assert st["stages"]["recorder"]["kind"] == "recorder" and "recorder_balanced" in st["accounting"]
    assert rec.parent.is_dir(), "--record made the folder before anything started"


def test_frame_id_is_the_chunks_own_else_the_default(tmp_path):
    """Issue 20 gives chunks a frame: the recorder takes ``chunk.frame_id`` when there is one."""
    rc = RecordConfig(path=str(tmp_path / "f.mcap"), frame_id="odom")
    rec = Recorder(rc, StageCounters(), __import__("logging").getLogger("t"))
    a, b = _c(3, 0), _c(3, 1)
    b.frame_id = "map"  # what ingest will set once it transforms into the fixed frame
    rec.add(a)
    rec.add(b)
    rec.close()
    assert [m.frame_id for m in read_recording(rc.path)] == ["odom", "map"]
