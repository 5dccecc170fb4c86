"""The ``rosbag`` transport replays pointflow's own recordings exactly: the same points,
channels, stamps and order, at the recorded timing; recording the replay gives the same file
contents again."""
from __future__ import annotations

import time

import numpy as np

from pointflow.config import load_config
from pointflow.ingest.transports.rosbag import RosbagTransport
from pointflow.runtime.pipeline import Pipeline

from .helpers import read_recording

CHANNELS = ["intensity", "classification", "beam", "range"]


def _pipeline(source: dict, rec: str, **over) -> dict:
    return {"source": source, "ring": {"max_points": 100_000},
            "render": {"backend": "cpu", "size": [64, 48], "output": {"every_n_frames": 1000}},
            "supervisor": {"max_restarts": 0, "hung_after_ms": 10_000},
            "record": {"path": rec, "channels": CHANNELS, "chunk_size": 50_000, "queue_messages": 1024}, **over}


def _run_to_end(cfg: dict, out) -> dict:
    with Pipeline.from_dict(cfg, out_dir=str(out)) as pipe:
        done = lambda: (pipe.stats()["stages"]["source"]["finished"] and pipe.stats()["stages"]["ingest"]["points_in"]
                        >= pipe.stats()["stages"]["source"]["points_out"] > 0)
        pipe.wait(60, until=done)
        assert done()
    return pipe.stats()


def _same(a, b) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.positions, y.positions)
        assert sorted(x.channels) == sorted(y.channels)
        for k in x.channels:
            np.testing.assert_array_equal(x.channels[k], y.channels[k])
        assert x.stamp_ns == y.stamp_ns


def test_replay_equals_the_recording(tmp_path):
    rec1, rec2 = str(tmp_path / "one.mcap"), str(tmp_path / "two.mcap")
    synth = {"transport": "synthetic", "options": {"points_per_scan": 4000, "chunks_per_scan": 8, "scans": 3,
                                                  "realtime": False, "channels": CHANNELS}}
    st1 = _run_to_end(_pipeline(synth, rec1), tmp_path / "o1")
    first = read_recording(rec1)
    assert len(first) == 24 and sum(m.n for m in first) == st1["stages"]["ingest"]["points_out"]
    assert sorted(first[0].channels) == sorted(CHANNELS)

    # the transport on its own: chunk for message, in order, at the recorded timing
    opts = load_config({"source": {"transport": "rosbag", "options": {"path": rec1, "rate": 1.0}}}).sources[0].options
    tr = RosbagTransport(opts, "replay")
    tr.open()
    got, t_yield = [], []
    t_start = time.monotonic()
    try:
        for c in tr.chunks():
            if c is not None:
                got.append(c)
                t_yield.append(time.monotonic())
    finally:
        tr.close()
    assert [c.source_id for c in got] == ["replay:/pointflow/source"] * len(first)
    for c, m in zip(got, first):
        np.testing.assert_array_equal(c.positions, m.positions)
        for k in CHANNELS:
            np.testing.assert_array_equal(c.channels[k], m.channels[k])
        assert c.stamp_ns == m.stamp_ns
    for k in range(1, len(got)):  # never released before its recorded offset (by log time)
        assert t_yield[k] - t_start >= (first[k].log_time - first[0].log_time) / 1e9

    # through a whole pipeline: the ring takes every recorded point, and recording the replay
    # gives the same messages again
    st2 = _run_to_end(_pipeline({"transport": "rosbag", "options": {"path": rec1, "rate": 0, "loop": False}}, rec2),
                      tmp_path / "o2")
    assert st2["ring"]["total_written"] == sum(m.n for m in first)
    assert st2["accounting"]["recorder_balanced"] and st2["accounting"]["lost_before_recorder"] == 0
    second = read_recording(rec2)
    assert {m.topic for m in second} == {"/pointflow/source/pointflow/source"}
    _same(first, second)


def test_split_recording_replays_as_one(tmp_path):
    rec = str(tmp_path / "split.mcap")
    synth = {"transport": "synthetic", "options": {"points_per_scan": 4000, "chunks_per_scan": 8, "scans": 3,
                                                  "realtime": False, "channels": CHANNELS}}
    cfg = _pipeline(synth, rec)
    cfg["record"]["split"] = {"size_mb": 0.1}
    _run_to_end(cfg, tmp_path / "o")
    parts = sorted(tmp_path.glob("split*.mcap"))
    assert len(parts) >= 3
    whole = [m for p in [tmp_path / "split.mcap", *sorted(tmp_path.glob("split.0*.mcap"))] for m in read_recording(str(p))]
    opts = load_config({"source": {"transport": "rosbag", "options": {"path": str(tmp_path / "split*.mcap"),
                                                                      "rate": 0}}}).sources[0].options
    tr = RosbagTransport(opts, "r")
    tr.open()
    try:
        got = [c for c in tr.chunks() if c is not None]
    finally:
        tr.close()
    assert len(got) == len(whole) == 24
    for c, m in zip(got, whole):
        np.testing.assert_array_equal(c.positions, m.positions)


def test_the_documented_record_then_replay_flow(tmp_path):
    """docs/record.md's first block, as a user runs it from a fresh clone: record the demo to
    out/demo.mcap, inspect it, replay it with configs/rosbag.yaml unchanged (its path is
    relative to the config file, so the copy keeps the clone's layout)."""
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    import yaml

    root = Path(__file__).resolve().parents[2]
    (tmp_path / "configs").mkdir()
    shutil.copy(root / "configs" / "rosbag.yaml", tmp_path / "configs" / "rosbag.yaml")
    demo = yaml.safe_load((root / "configs" / "demo.yaml").read_text())
    demo["render"] = {"backend": "cpu", "size": [64, 48], "output": {"every_n_frames": 1000}}
    demo["supervisor"] = {"hung_after_ms": 10_000}
    demo["record"] = {"path": str(tmp_path / "out" / "demo.mcap")}
    with Pipeline.from_dict(demo, out_dir=str(tmp_path / "o1")) as pipe:
        pipe.wait(60, until=lambda: (pipe.stats().get("stages", {}).get("recorder") or {}).get("record_messages", 0) >= 3)
        assert pipe.stats()["stages"]["recorder"]["record_messages"] >= 3
    mcap = tmp_path / "out" / "demo.mcap"
    recorded = read_recording(str(mcap))
    assert recorded

    exe = [sys.executable, "-c", "import sys; from pointflow.cli import main; sys.exit(main())"]
    ins = subprocess.run(exe + ["inspect", str(mcap)], capture_output=True, text=True, timeout=120)
    assert ins.returncode == 0, ins.stderr
    assert "summary: intact" in ins.stdout and f"{len(recorded)} messages" in ins.stdout

    cfg = yaml.safe_load((tmp_path / "configs" / "rosbag.yaml").read_text())
    cfg["source"]["options"].update(rate=0, loop=False)
    cfg["render"] = {"backend": "cpu", "size": [64, 48], "output": {"every_n_frames": 1000}}
    cfg["supervisor"] = {"max_restarts": 0, "hung_after_ms": 10_000}
    (tmp_path / "configs" / "replay.yaml").write_text(yaml.safe_dump(cfg))
    with Pipeline.from_yaml(str(tmp_path / "configs" / "replay.yaml"), out_dir=str(tmp_path / "o2")) as pipe:
        total = sum(m.n for m in recorded)
        pipe.wait(60, until=lambda: pipe.stats()["ring"]["total_written"] >= total)
        assert pipe.stats()["ring"]["total_written"] == total
