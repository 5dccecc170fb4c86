"""The rosbag transport on recordings written by the test with the rosbags writers: ROS 1
.bag, ROS 2 sqlite3 and MCAP bag folders, a bare .mcap; through the real source and ingest
processes into the ring, and its options and errors at the transport level."""
import os

import numpy as np
import pytest

from pointflow.config import ConfigError
from pointflow.ingest.transports import resolve_transport

from . import ros_util as ru
from .stage_util import base_config

SEC = 1_000_000_000
KINDS = ["ros1", "sqlite3", "mcap", "bare_mcap"]


def _recording():
    """(topic, bag time, cloud, rejected reason or None): every layout once, more Ouster-like
    scans, and one broken message of each reason between good ones."""
    msgs, t = [], SEC
    clouds = ru.all_clouds()
    order = ["/os/points", "/be", "/unsorted", "/count", "/organised", "/rgb", "/rgba"]
    for i, topic in enumerate(order):
        msgs.append((topic, t, clouds[topic], None))
        t += SEC // 4
        if i < len(ru.REJECT_KINDS):
            kind = ru.REJECT_KINDS[i]
            msgs.append(("/os/points", t, ru.broken(kind, seed=20 + i), kind))
            t += SEC // 4
    for k in range(3):
        msgs.append(("/os/points", t, ru.cloud_padded(100 + k, n=50), None))
        t += SEC // 4
    return msgs


def _name(kind):
    return {"ros1": "rec.bag", "sqlite3": "rec_sqlite", "mcap": "rec_mcap", "bare_mcap": "rec.mcap"}[kind]


def _write(tmp_path, kind, msgs=None):
    msgs = msgs if msgs is not None else _recording()
    return ru.write_bag(tmp_path / _name(kind), kind, [(tp, t, c) for tp, t, c, _ in msgs])


def _transport(path, **opts):
    cls = resolve_transport("rosbag")
    o = cls.validate_options({"path": str(path), "rate": 0, **opts}, "sources[0].options", os.getcwd())
    t = cls(o, "bag")
    t.open()
    return t


def _replay(path, limit=10_000, **opts):
    t = _transport(path, **opts)
    try:
        out = []
        for c in t.chunks():
            if c is not None:
                out.append(c)
                if len(out) >= limit:
                    break
        return out, t
    finally:
        t.close()


@pytest.mark.parametrize("kind", KINDS)
def test_every_storage_replays_through_source_and_ingest_into_the_ring_exactly(tmp_path, kind):
    msgs = _recording()
    path = _write(tmp_path, kind, msgs)
    good = [(tp, c) for tp, _, c, bad in msgs if bad is None]
    total = sum(c.n for _, c in good)
    cfg = base_config()
    cfg["source"] = {"transport": "rosbag", "options": {"path": str(path), "rate": 0}}
    cfg["ring"]["extra_channels"] = ["intensity", "rgb", "ring"]
    st = ru.SourceIngest(cfg)
    try:
        stats = st.wait_ingest(lambda s: s["points_in"] == total and s.get("chunks_accepted") == len(good))
        st.wait_stats(lambda s: "source" in st.done)  # the replay ended on its own
        src = st.stage_stats["source"]
        for kind_ in ru.REJECT_KINDS:
            assert src[f"transport_rejected_{kind_}"] == 1, kind_
        assert src["transport_messages"] == len(msgs) and src["points_out"] == total
        exp = [c.expected(keep_nan=False) for _, c in good]
        nan = sum(c.n for _, c in good) - sum(p.shape[0] for p, _ in exp)
        assert nan > 0 and stats["drops"] == {"non_finite": nan}
        assert stats["points_out"] == total - nan
        snap = st.ring.snapshot()
        want_pos = np.concatenate([p.astype(np.float64) for p, _ in exp])
        assert np.array_equal(snap.positions, want_pos)  # exact: bytes -> decoder -> wire -> ring
        for name in ("intensity", "ring"):
            has = np.concatenate([np.full(p.shape[0], name in ch) for p, ch in exp])
            vals = np.concatenate([ch[name].astype(np.float32) if name in ch else np.zeros(p.shape[0], np.float32)
                                   for p, ch in exp])
            assert np.array_equal(snap.present[name], has), name
            assert np.array_equal(snap.channels[name][has], vals[has]), name
        has = np.concatenate([np.full(p.shape[0], "rgb" in ch) for p, ch in exp])
        rgb = np.concatenate([ch["rgb"] if "rgb" in ch else np.zeros((p.shape[0], 3), np.uint8) for p, ch in exp])
        assert has.sum() == 60 and np.array_equal(snap.channels["rgb"][has], rgb[has])
    finally:
        st.close()


@pytest.mark.parametrize("kind", ["mcap", "bare_db3"])
def test_topics_source_ids_header_stamps_and_count_fields(tmp_path, kind):
    path = _write(tmp_path, kind) if kind != "bare_db3" else \
        ru.write_bag(tmp_path / "rec.db3", kind, [(tp, t, c) for tp, t, c, _ in _recording()])
    chunks, t = _replay(path, topics=["/count", "/be"])
    clouds = ru.all_clouds()
    assert [c.source_id for c in chunks] == ["bag:/be", "bag:/count"]  # recording order
    assert [c.stamp_ns for c in chunks] == [clouds["/be"].stamp_ns, clouds["/count"].stamp_ns]
    assert chunks[1].channels["normal"].shape == (25, 3)
    assert np.array_equal(chunks[1].channels["normal"], clouds["/count"].values["normal"])
    assert np.array_equal(chunks[0].positions, clouds["/be"].expected()[0]) and chunks[0].positions.dtype == np.float64
    assert t.counters["messages"] == 2 and t.counters["rejected"] == 0


@pytest.mark.parametrize("kind,compression", [("ros1", "bz2"), ("ros1", "lz4"), ("sqlite3", "message"),
                                              ("mcap", "file")])
def test_compressed_recordings(tmp_path, kind, compression):
    msgs = [("/os/points", SEC * (k + 1), ru.cloud_padded(k, n=30), None) for k in range(3)] + \
        [("/organised", 5 * SEC, ru.cloud_organised(), None)]
    path = ru.write_bag(tmp_path / ("c.bag" if kind == "ros1" else "c"), kind, [(tp, t, c) for tp, t, c, _ in msgs],
                        compression=compression)
    chunks, t = _replay(path)
    assert len(chunks) == 4 and t.counters["rejected"] == 0
    for chunk, (_, _, cloud, _) in zip(chunks, msgs):
        pos, ch = cloud.expected()
        assert np.array_equal(chunk.positions, pos, equal_nan=True)
        assert all(np.array_equal(chunk.channels[k], v) for k, v in ch.items())


def test_split_ros1_bags_by_glob_replay_together_in_time_order(tmp_path):
    a = [("/os/points", SEC * k, ru.cloud_padded(k, n=10), None) for k in (1, 3, 5)]
    b = [("/os/points", SEC * k, ru.cloud_padded(k, n=10), None) for k in (2, 4)]
    ru.write_bag(tmp_path / "run_0.bag", "ros1", [(tp, t, c) for tp, t, c, _ in a])
    ru.write_bag(tmp_path / "run_1.bag", "ros1", [(tp, t, c) for tp, t, c, _ in b])
    chunks, _ = _replay(tmp_path / "run_*.bag")
    assert [c.stamp_ns for c in chunks] == [ru.cloud_padded(k, n=10).stamp_ns for k in (1, 2, 3, 4, 5)]
    cls = resolve_transport("rosbag")
    ru.write_bag(tmp_path / "run_x", "mcap", [(tp, t, c) for tp, t, c, _ in b])
    with pytest.raises(ConfigError, match=r"options\.path.*matches 3 paths; only split ROS 1 \.bag"):
        cls.validate_options({"path": str(tmp_path / "run_*")}, "sources[0].options", os.getcwd())


def test_ros2_bag_without_message_definitions_as_humble_records_them(tmp_path):
    msgs = [("/os/points", SEC, ru.cloud_padded(), None), ("/rgb", 2 * SEC, ru.cloud_rgb(), None)]
    path = _write(tmp_path, "sqlite3", msgs)
    ru.strip_definitions(path)
    chunks, _ = _replay(path)
    assert [c.source_id for c in chunks] == ["bag:/os/points", "bag:/rgb"]
    assert np.array_equal(chunks[1].channels["rgb"], ru.cloud_rgb().expected()[1]["rgb"])
    assert np.array_equal(chunks[0].positions, ru.cloud_padded().expected()[0])


def test_start_end_window_loop_rename_and_channels(tmp_path):
    msgs = [("/os/points", SEC * (k + 1), ru.cloud_padded(k, n=10), None) for k in range(5)]
    path = _write(tmp_path, "sqlite3", msgs)
    chunks, _ = _replay(path, start=1.0, end=3.5)  # recording starts at the first message (1 s)
    assert [c.stamp_ns for c in chunks] == [msgs[k][2].stamp_ns for k in (1, 2, 3)]
    chunks, t = _replay(path, loop=True, limit=12, rename={"reflectivity": "intensity", "intensity": "power"},
                        channels=["intensity"])
    assert [c.stamp_ns for c in chunks] == [m[2].stamp_ns for m in msgs] * 2 + [m[2].stamp_ns for m in msgs[:2]]
    assert t.counters["loops"] == 2
    assert set(chunks[0].channels) == {"intensity"}
    assert np.array_equal(chunks[0].channels["intensity"], msgs[0][2].values["reflectivity"])


def test_recorded_timing_paces_the_replay_in_order(tmp_path):
    msgs = [("/os/points", SEC * (k + 1) // 5, ru.cloud_padded(k, n=5), None) for k in range(4)]
    path = _write(tmp_path, "ros1", msgs)
    t = _transport(path, rate=1.0)
    try:
        items = []
        for c in t.chunks():
            items.append(c)
            if sum(x is not None for x in items) == 4:
                break
    finally:
        t.close()
    got = [c for c in items if c is not None]
    assert [c.stamp_ns for c in got] == [m[2].stamp_ns for m in msgs]
    assert None in items  # the transport waited for recorded time (idle ticks), it did not burst


def test_progress_is_for_the_progress_line_not_drawn_here(tmp_path, capsys):
    """Issue 31.7: the transport's own bar fought the run's progress line and log lines on a
    terminal; it now only counts the share replayed (``transport_progress``)."""
    path = _write(tmp_path, "ros1")
    _, t = _replay(path, progress="on")
    assert t.counters["progress"] == 1.0
    assert capsys.readouterr().err == ""
    _, t = _replay(path, progress="off")
    assert "progress" not in t.counters


def test_bad_topics_and_files_are_config_errors_listing_the_pointcloud2_topics(tmp_path):
    path = _write(tmp_path, "ros1")
    cls = resolve_transport("rosbag")

    def check(opts):
        cls.validate_options({"path": str(path), **opts}, "sources[0].options", os.getcwd())

    with pytest.raises(ConfigError, match=r"sources\[0\]\.options\.topics\[1\].*'/nope' is not in the recording.*"
                                          r"/be \(1 messages\).*/os/points \(8 messages\)"):
        check({"topics": ["/be", "/nope"]})
    with pytest.raises(ConfigError, match=r"topics\[0\].*'/chatter' is a std_msgs/msg/String, not a PointCloud2.*/rgba"):
        check({"topics": ["/chatter"]})
    with pytest.raises(ConfigError, match=r"options\.start.*past the end of the recording"):
        check({"start": 1000})
    with pytest.raises(ConfigError, match=r"options\.end.*must be after start"):
        check({"start": 2, "end": 1})
    with pytest.raises(ConfigError, match=r"options\.rate.*>= 0"):
        check({"rate": -1})
    with pytest.raises(ConfigError, match=r"options\.path.*no such file"):
        cls.validate_options({"path": str(tmp_path / "missing.bag")}, "sources[0].options", os.getcwd())
    (tmp_path / "junk.bag").write_bytes(b"#ROSBAG V2.0\n" + b"\0" * 100)
    with pytest.raises(ConfigError, match=r"options\.path.*junk.bag.*cannot read"):
        cls.validate_options({"path": str(tmp_path / "junk.bag")}, "sources[0].options", os.getcwd())
    only_strings = tmp_path / "strings"
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore
    ts = get_typestore(Stores.ROS2_HUMBLE)
    with Writer(only_strings, version=9) as w:
        c = w.add_connection("/chatter", "std_msgs/msg/String", typestore=ts)
        w.write(c, 1, ts.serialize_cdr(ts.types["std_msgs/msg/String"](data="x"), "std_msgs/msg/String"))
    with pytest.raises(ConfigError, match=r"no PointCloud2 topics \(topics: /chatter \(std_msgs/msg/String\)\)"):
        cls.validate_options({"path": str(only_strings)}, "sources[0].options", os.getcwd())


def test_a_rejected_message_names_its_topic(tmp_path, caplog):
    """A bag of several topics: the rejection line names the topic of the broken message
    (stats count by reason only, so which topic was broken could not be told)."""
    import logging

    msgs = [("/good", SEC, ru.cloud_padded(1, n=20), None),
            ("/front/points", SEC + SEC // 4, ru.broken(ru.REJECT_KINDS[0], seed=3), ru.REJECT_KINDS[0]),
            ("/good", SEC + SEC // 2, ru.cloud_padded(2, n=20), None)]
    path = _write(tmp_path, "mcap", msgs)
    caplog.set_level(logging.WARNING)
    chunks, t = _replay(path, topics=["/good", "/front/points"])
    assert len(chunks) == 2 and t.counters["rejected"] == 1
    lines = [r.getMessage() for r in caplog.records if "rejected message" in r.getMessage()]
    assert len(lines) == 1 and f"[{ru.REJECT_KINDS[0]}]" in lines[0] and "topic /front/points: " in lines[0], lines
