"""``ros2_zenoh``: live ROS 2 over rmw_zenoh without ROS. Real processes throughout: a Zenoh
router, a publisher that behaves as rmw_zenoh's (``pointflow/testing/rmw_zenoh_pub.py``: its keys, attachments,
liveliness tokens, transient-local cache, Humble and buffer-aware Rolling modes), and the real
source and ingest stages feeding a ring (or ``pointflow run``)."""
from __future__ import annotations

import os
import pickle
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("zenoh", reason="eclipse-zenoh comes with the remote extra: pip install 'pointflow[remote]'")
pytest.importorskip("rosbags", reason="rosbags comes with the ros extra: pip install 'pointflow[ros]'")

from pointflow.config import ConfigError, load_config  # noqa: E402
from pointflow.ingest import rmw_zenoh as rz  # noqa: E402
from pointflow.testing import rmw_zenoh_pub as P  # noqa: E402
from pointflow.testing import LineProc, free_port  # noqa: E402

from . import ros_util as ru  # noqa: E402
from .stage_util import base_config  # noqa: E402

PUB = P.__name__  # run with -m
TOPIC = "/ouster/points"
REPO = Path(__file__).resolve().parents[2]


class Proc(LineProc):
    """The publisher (or router) as a helper process whose stdout lines are read on a thread."""

    def __init__(self, args: list[str]):
        super().__init__(["-m", PUB, *args])


@pytest.fixture
def router():
    loc = f"tcp/127.0.0.1:{free_port()}"
    r = Proc(["--router", loc])
    try:
        r.wait_line("READY")
        yield loc
    finally:
        r.close()


def start_publisher(tmp_path: Path, spec: dict) -> Proc:
    path = tmp_path / f"spec-{time.monotonic_ns()}.pickle"
    path.write_bytes(pickle.dumps(spec))
    p = Proc([str(path)])
    p.wait_line("READY")
    return p


def source_cfg(loc: str, **opts) -> dict:
    cfg = base_config()
    cfg["ring"]["extra_channels"] = ["intensity"]
    cfg["source"] = {"transport": "ros2_zenoh",
                     "options": {"topic": TOPIC, "zenoh": {"connect": [loc]}, "discovery_timeout_s": 10,
                                 "queue_messages": 256, **opts}}  # exact counts on a loaded machine
    return cfg


def wait_ingest(st, pred, timeout: float = 90.0) -> dict:
    """st.wait_ingest, with the source's counters in the message when it times out."""
    try:
        return st.wait_ingest(pred, timeout=timeout)
    except AssertionError as exc:
        raise AssertionError(f"{exc}; source stats {st.stage_stats.get('source')}") from None


# ----------------------------------------------------------------------------- the protocol
def test_keys_tokens_and_attachment_follow_rmw_zenoh():
    assert rz.dds_type("sensor_msgs/msg/PointCloud2") == "sensor_msgs::msg::dds_::PointCloud2_"
    assert rz.ros_type("tf2_msgs::msg::dds_::TFMessage_") == "tf2_msgs/msg/TFMessage"
    assert rz.topic_key(0, "/ouster/points", "sensor_msgs/msg/PointCloud2") == \
        "0/ouster/points/sensor_msgs::msg::dds_::PointCloud2_/*"
    # a token as rmw_zenoh's own docs show one (talker, /chatter, depth 7)
    h = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
    key = f"@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/11/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/{h}/::,7:,:,:,,"
    e = rz.parse_token(key)
    assert (e.kind, e.topic, e.type, e.type_hash, e.node, e.namespace, e.entity_id) == \
        ("MP", "/chatter", "std_msgs/msg/String", h, "talker", "/", "11")
    assert e.key() == key
    node = rz.parse_token("@ros2_lv/5/abc/3/3/NN/%/%robot1/driver")
    assert (node.kind, node.domain_id, node.namespace, node.node) == ("NN", 5, "/robot1", "driver")
    for bad in ("@ros2_lv/0/abc/0/1/MP/%/%/talker", "@ros2_lv/x/abc/0/0/NN/%/%/n", "other/0/a/0/0/NN/%/%/n",
                "@ros2_lv/0/abc/0/1/XX/%/%/n/%t/T/h/q"):
        assert rz.parse_token(bad) is None, bad
    assert rz.qos_chunk(rz.BEST_EFFORT, rz.VOLATILE, 5) == "2::,5:,:,:,,"
    assert rz.qos_chunk(rz.RELIABLE, rz.TRANSIENT_LOCAL, 1) == ":1:,1:,:,:,,"
    assert rz.qos_chunk() == "::,:,:,:,,"

    # the attachment, byte for byte: int64 LE, int64 LE, LEB128 length 16, the GID
    gid = bytes(range(100, 116))
    raw = rz.encode_attachment(42, 1_700_000_000_123_456_789, gid).to_bytes()
    assert raw == struct.pack("<qqB", 42, 1_700_000_000_123_456_789, 16) + gid
    att = rz.parse_attachment(raw)
    assert (att.sequence_number, att.source_timestamp_ns, att.gid) == (42, 1_700_000_000_123_456_789, gid)
    keyed = b"".join(bytes([len(k)]) + k.encode() + v for k, v in (
        ("sequence_number", struct.pack("<q", 7)), ("source_timestamp", struct.pack("<q", 9)),
        ("source_gid", bytes([16]) + gid)))
    assert rz.parse_attachment(keyed) == rz.Attachment(7, 9, gid)
    for bad in (None, b"", b"abc", struct.pack("<qqB", 1, 2, 5) + bytes(5)):
        with pytest.raises(rz.AttachmentError):
            rz.parse_attachment(bad)

    led = rz.SequenceLedger()
    a, b = bytes(16), bytes([1]) * 16
    for seq in (5, 6, 9, 8, 10):  # joined at 5, lost 7 and 8? no: 8 arrives late, counted out of order
        led.observe("/t", rz.Attachment(seq, 0, a))
    led.observe("/t", rz.Attachment(1, 0, b))
    led.observe("/t", rz.Attachment(3, 0, b))
    c = led.counters()
    assert c["lost_in_transit_messages"] == 2 + 1 and c["out_of_order"] == 1 and c["joined_after_messages"] == 4
    assert c[f"lost_in_transit_messages:/t@{a.hex()}"] == 2 and c[f"lost_in_transit_messages:/t@{b.hex()}"] == 1


def test_buffer_aware_tokens_keys_and_gids_follow_rmw_zenoh_0_12():
    """rmw_zenoh 0.12.0 / 0.10.5 (liveliness_utils.cpp, buffer_endpoint_helpers.hpp): a 14th token
    chunk ``backends:<name>:<meta>;...`` (sorted, ``% ; : /`` escaped), the GID as XXH3-128 of
    the token (low 64 bits first, little-endian), ``_buf_cpu`` and ``_buf/<gid hex>`` keys."""
    h = "RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5"
    base = f"0/ouster/points/sensor_msgs::msg::dds_::PointCloud2_/{h}"
    pub = rz.Entity(0, "aac3178e146ba6f1fc6e6a4085e77f21", "0", "1", "MP", "/", "/", "driver", TOPIC, P.PC2, h,
                    "2::,5:,:,:,,", backends=dict(rz.CPU_ONLY))
    key = pub.key()
    assert key == (f"@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/1/MP/%/%/driver/%ouster%points/"
                   f"sensor_msgs::msg::dds_::PointCloud2_/{h}/2::,5:,:,:,,/backends:cpu:")
    back = rz.parse_token(key)
    assert back == pub and back.buffer_aware and back.cpu_only
    jazzy = rz.parse_token(key.rsplit("/", 1)[0])               # the same token without the chunk
    assert jazzy.backends is None and not jazzy.buffer_aware and not jazzy.cpu_only
    odd = {"cuda": "dev:0/a;b%", "cpu": ""}
    assert rz.backends_chunk(odd) == "backends:cpu:;cuda:dev%3A0%2Fa%3Bb%25"
    assert rz.parse_backends(rz.backends_chunk(odd)) == odd and rz.parse_backends("backends:") is None
    many = rz.parse_token(key.replace("backends:cpu:", rz.backends_chunk(odd)))
    assert many.backends == odd and not many.cpu_only       # served on _buf/<gid>, not _buf_cpu
    # XXH3-128 of the empty input is 99aa06d3014798d8 6001c324468d497f (xxHash's test vector):
    # rmw_zenoh copies the low half first, each little-endian
    assert rz.gid("").hex() == "7f498d4624c30160" + "d8984701d306aa99"
    assert pub.gid() == rz.gid(key) and len(pub.gid()) == 16 and pub.gid() != jazzy.gid()
    assert rz.buffer_cpu_key(base) == base + "/_buf_cpu"
    assert rz.buffer_key(base, bytes(range(16))) == base + "/_buf/000102030405060708090a0b0c0d0e0f"
    assert rz.BUFFER_TYPES == {P.PC2}
    # a _buf_cpu reader's sequence numbers step by 1 + the publisher's other subscriptions
    led, g = rz.SequenceLedger(), bytes(16)
    for seq in (1, 3, 5, 9, 11):     # stride 2 (one other subscription); 7 lost
        led.observe("/t", rz.Attachment(seq, 0, g), stride=2)
    assert led.counters()["lost_in_transit_messages"] == 1
    led = rz.SequenceLedger()
    for seq in (2, 4, 6, 8):         # the graph says 1 (the other subscription left: the publisher
        led.observe("/t", rz.Attachment(seq, 0, g), stride=1)   # still serves it), steps say 2
    assert led.counters()["lost_in_transit_messages"] == 0


# ----------------------------------------------------------------------------- end to end
@pytest.mark.parametrize("mode,domain", [("jazzy", 0), ("humble", 0), ("rolling", 3)])
def test_clouds_arrive_exactly_and_skipped_sequence_numbers_count_as_lost(tmp_path, router, mode, domain):
    clouds = [ru.cloud_padded(k, n=64 + k) for k in range(6)]
    script = [("put", TOPIC, P.cdr_cloud(c)) for c in clouds[:2]]
    script += [("skip", TOPIC), ("skip", TOPIC)]                          # two lost on the way
    script += [("put", TOPIC, P.cdr_cloud(c)) for c in clouds[2:4]]
    script += [("put", TOPIC, b"\x00\x01\x00\x00" + b"\x07" * 11)]        # not a PointCloud2: rejected
    script += [("skip", TOPIC)] + [("put", TOPIC, P.cdr_cloud(c)) for c in clouds[4:]]
    pub = start_publisher(tmp_path, {"connect": router, "mode": mode, "domain": domain,
                                     "advertise": [(TOPIC, P.PC2), ("/front/points", P.PC2)], "script": script})
    st = None
    try:
        st = ru.SourceIngest(source_cfg(router, domain_id=domain))
        matched = rz.parse_token(pub.wait_line("MATCHED").split()[1])
        path = pub.wait_line("PATH", timeout=60) if mode == "rolling" else None
        if mode != "rolling":  # rmw_zenoh before 0.10.5 publishes whether or not anyone listens
            pub.send("go\n")
        assert pub.wait_line("SENT") == f"SENT {TOPIC} 7"
        want = sum(c.n for c in clouds)
        stats = wait_ingest(st, lambda s: s.get("points_out") == want)
        # the source reports on its own heartbeat: wait for the one after the last message
        src = st.wait_stats(lambda s: st.stage_stats.get("source", {}).get("transport_messages") == 7) and \
            st.stage_stats["source"]
        snap = st.ring.snapshot()
    finally:
        if st is not None:
            st.close()
        pub.close()
    # our own subscription token, as rmw_zenoh declares it, with the publishers' type hash, and
    # (PointCloud2 has buffer fields) as a CPU-only buffer-aware subscription: backends:cpu:
    assert (matched.kind, matched.topic, matched.type, matched.node, matched.domain_id) == \
        ("MS", TOPIC, P.PC2, "pointflow", domain)
    assert matched.backends == {"cpu": ""} and matched.key().endswith("/2::,5:,:,:,,/backends:cpu:")
    if mode == "rolling":  # a buffer-aware publisher served us on <key>/_buf_cpu, never the base key
        assert path == f"PATH cpu {matched.key()}"
        assert src["transport_buffer_cpu_messages"] == 7
    else:
        assert "transport_buffer_cpu_messages" not in src
    assert matched.type_hash == (rz.HUMBLE_HASH if mode == "humble" else
                                 "RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5")
    assert stats["drops"] == {} and stats["points_out"] == want
    assert np.array_equal(snap.positions, np.concatenate([c.expected()[0] for c in clouds]).astype(np.float64))
    assert np.array_equal(snap.channels["intensity"], np.concatenate([c.values["intensity"] for c in clouds]))
    assert src["transport_points"] == want and src["transport_lost_in_transit_messages"] == 3
    assert src["transport_rejected_decode_error"] == 1 and src["transport_publishers_seen"] == 1
    per_pub = {k: v for k, v in src.items() if k.startswith("transport_lost_in_transit_messages:")}
    assert list(per_pub.values()) == [3] and list(per_pub)[0].startswith(f"transport_lost_in_transit_messages:{TOPIC}@")
    assert src["transport_graph_publishers"] == 2


def test_a_rolling_publisher_serves_an_old_subscription_on_its_gid_key_and_ours_on_buf_cpu(tmp_path, router):
    """Against a buffer-aware (Rolling 0.12.0) publisher: the subscription token the source
    declared before (no backends chunk) and its base-key subscriber get nothing on the base key
    (the reported 0 of 6): that subscription is served on ``<key>/_buf/<its GID>``; the source,
    CPU-only, gets every cloud on ``_buf_cpu``, and three skipped messages count as 3 lost
    although each message uses two sequence numbers."""
    import zenoh

    clouds = [ru.cloud_padded(k, n=40 + k) for k in range(6)]
    script = [("put", TOPIC, P.cdr_cloud(c)) for c in clouds[:3]] + [("skip", TOPIC)] * 3
    script += [("put", TOPIC, P.cdr_cloud(c)) for c in clouds[3:]]
    h = "RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5"
    base = rz.topic_key(0, TOPIC, P.PC2, h)
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", f'["{router}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    old = zenoh.open(conf)
    got: dict[str, list] = {"base": [], "gid": []}
    # exactly what ros2_zenoh declared before: a subscriber on the base key and a token without backends
    token = rz.Entity(0, str(old.zid()), "0", "1", "MS", "/", "/", "old_viewer", TOPIC, P.PC2, h,
                      rz.qos_chunk(rz.BEST_EFFORT, rz.VOLATILE, 5))
    subs = [old.declare_subscriber(rz.topic_key(0, TOPIC, P.PC2), lambda s: got["base"].append(s.attachment)),
            old.declare_subscriber(rz.buffer_key(base, token.gid()),
                                   lambda s: got["gid"].append(rz.parse_attachment(s.attachment)))]
    tok = old.liveliness().declare_token(token.key())
    graph: list[rz.Entity] = []
    subs.append(old.liveliness().declare_subscriber(
        "@ros2_lv/0/**", lambda s: s.kind == zenoh.SampleKind.PUT and graph.append(rz.parse_token(str(s.key_expr))),
        history=True))
    pub = start_publisher(tmp_path, {"connect": router, "mode": "rolling", "advertise": [(TOPIC, P.PC2)],
                                     "script": script, "min_subscribers": 2})
    st = None
    try:
        st = ru.SourceIngest(source_cfg(router))
        paths = {pub.wait_line("PATH", timeout=60) for _ in range(2)}
        assert pub.wait_line("SENT") == f"SENT {TOPIC} 6"
        want = sum(c.n for c in clouds)
        stats = wait_ingest(st, lambda s: s.get("points_out") == want)
        src = st.wait_stats(lambda s: st.stage_stats.get("source", {}).get("transport_messages") == 6) and \
            st.stage_stats["source"]
        snap = st.ring.snapshot()
        end = time.monotonic() + 30
        while len(got["gid"]) < 6 and time.monotonic() < end:
            time.sleep(0.05)
    finally:
        if st is not None:
            st.close()
        pub.close()
        tok.undeclare()
        for sub in subs:
            sub.undeclare()
        old.close()
    ours = [e for e in graph if e and e.kind == "MS" and e.node == "pointflow"]
    pubs = [e for e in graph if e and e.kind == "MP"]
    assert len(ours) == 1 and ours[0].cpu_only
    assert paths == {f"PATH gid {token.gid().hex()} {token.key()}", f"PATH cpu {ours[0].key()}"}
    # the publisher's token ends backends:cpu:, and its GID in every attachment is XXH3-128 of it
    assert len(pubs) == 1 and pubs[0].key().endswith("/backends:cpu:") and pubs[0].cpu_only
    assert got["base"] == []                                    # the old subscription: 0 of 6
    assert len(got["gid"]) == 6 and {a.gid for a in got["gid"]} == {pubs[0].gid()}
    assert [a.sequence_number for a in got["gid"]] == [2, 4, 6, 14, 16, 18]   # cpu put first, then this one
    assert stats["drops"] == {} and stats["points_out"] == want
    assert np.array_equal(snap.positions, np.concatenate([c.expected()[0] for c in clouds]).astype(np.float64))
    assert src["transport_buffer_cpu_messages"] == 6 and src["transport_lost_in_transit_messages"] == 3


def test_a_humble_publisher_that_starts_later_is_matched_and_read(tmp_path, router):
    """No publisher at start: the source waits (our subscription token carries the RIHS01 hash
    of the type); when a Humble publisher appears it adds a token with Humble's hash chunk."""
    clouds = [ru.cloud_padded(k, n=50) for k in range(3)]
    st = ru.SourceIngest(source_cfg(router, discovery_timeout_s=0.5))
    pub = None
    try:
        st.wait_stats(lambda s: "transport_graph_publishers" in st.stage_stats.get("source", {}))
        pub = start_publisher(tmp_path, {"connect": router, "mode": "humble", "advertise": [(TOPIC, P.PC2)],
                                         "script": [("put", TOPIC, P.cdr_cloud(c)) for c in clouds]})
        hashes = set()
        while len(hashes) < 2:  # both tokens, in whichever order the graph delivers them
            hashes.add(rz.parse_token(pub.wait_line("MATCHED").split()[1]).type_hash)
        pub.send("go\n")
        stats = wait_ingest(st, lambda s: s.get("points_out") == 150)
        snap = st.ring.snapshot()
    finally:
        st.close()
        if pub is not None:
            pub.close()
    assert hashes == {rz.HUMBLE_HASH, "RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5"}
    assert stats["drops"] == {}
    assert np.array_equal(snap.positions, np.concatenate([c.expected()[0] for c in clouds]).astype(np.float64))


def test_a_slow_reader_drops_its_oldest_clouds_counted_never_transforms_and_no_loss(tmp_path, router):
    """The transport in this process, not read while a real publisher sends: its queue keeps
    the newest ``queue_messages`` clouds, counts the rest, keeps every transform, and the
    sequence ledger (taken on arrival) sees no loss on the way."""
    from pointflow.frames.message import Transforms
    from pointflow.ingest.transports import resolve_transport

    clouds = [ru.cloud_padded(k, n=30) for k in range(6)]
    script = []
    for k, c in enumerate(clouds):
        script += [("put", "/tf", P.cdr_tf([("odom", "base_link", c.stamp_ns, (k, 0, 0), (0, 0, 0, 1))])),
                   ("put", TOPIC, P.cdr_cloud(c))]
    pub = start_publisher(tmp_path, {"connect": router, "mode": "jazzy", "script": script,
                                     "advertise": [(TOPIC, P.PC2), ("/tf", P.TFM)]})
    cls = resolve_transport("ros2_zenoh")
    t = cls(cls.validate_options({"topic": TOPIC, "zenoh": {"connect": [router]}, "queue_messages": 2,
                                  "tf_topics": ["/tf"]}, "options"), "src")
    t.wants_transforms = True
    try:
        t.open()
        assert {rz.parse_token(pub.wait_line("MATCHED").split()[1]).topic for _ in range(2)} == {TOPIC, "/tf"}
        pub.send("go\n")
        pub.wait_line("SENT")
        end = time.monotonic() + 20
        while t.counters["dropped_queue_full"] < 4 and time.monotonic() < end:
            time.sleep(0.05)
        got, it = [], t.chunks()
        while True:
            item = next(it)
            if item is None:
                break
            got.append(item)
    finally:
        t.close()
        pub.close()
    tfs = [g for g in got if isinstance(g, Transforms)]
    kept = [g for g in got if not isinstance(g, Transforms)]
    assert t.counters["dropped_queue_full"] == 4
    assert [c.stamp_ns for c in kept] == [c.stamp_ns for c in clouds[-2:]]          # the newest two
    assert [b.transforms[0].translation[0] for b in tfs] == [float(k) for k in range(6)]  # every transform
    assert t.counters["lost_in_transit_messages"] == 0 and t.counters["publishers_seen"] == 2


def _run(tmp_path: Path, cfg: dict, duration: str = "30") -> subprocess.CompletedProcess:
    import yaml

    path = tmp_path / f"cfg-{time.monotonic_ns()}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, "-m", "pointflow.cli", "run", str(path), "--duration", duration, "-q"],
                          capture_output=True, text=True, timeout=120, env=env, cwd=tmp_path)


def test_a_wrong_topic_fails_the_run_listing_the_pointcloud2_topics(tmp_path, router):
    pub = start_publisher(tmp_path, {"connect": router, "mode": "jazzy", "script": [],
                                     "advertise": [(TOPIC, P.PC2), ("/front/points", P.PC2),
                                                   ("/chatter", "std_msgs/msg/String")]})
    try:
        cfg = source_cfg(router, topic="/rear/points", discovery_timeout_s=2)
        cfg["render"]["output"] = {"dir": str(tmp_path / "out")}
        wrong = _run(tmp_path, cfg)
        cfg["source"]["options"]["topic"] = "/chatter"
        other_type = _run(tmp_path, cfg)
    finally:
        pub.close()
    for r in (wrong, other_type):
        assert r.returncode == 2, (r.returncode, r.stderr[-3000:])
        assert "Traceback" not in r.stderr, r.stderr[-3000:]
        assert "PointCloud2 topics published on domain 0: /front/points (1 publisher), /ouster/points (1 publisher)" \
            in r.stderr, r.stderr[-3000:]
    assert "topic '/rear/points' has no publisher" in wrong.stderr
    assert "topic '/chatter' is a std_msgs/msg/String, not a sensor_msgs/msg/PointCloud2" in other_type.stderr


def test_tf_and_cached_tf_static_place_the_clouds_in_the_fixed_frame(tmp_path, router):
    from frames import truth as T

    robot = T.Robot(n_tf=81)
    ext = T.extrinsic([0.9, 0.0, 1.7], [0, 2, 30])
    clouds = [ru.cloud_padded(k, n=40) for k in range(4)]
    script = []
    for k, (st_ns, R, p) in enumerate(robot.tf()):
        script.append(("put", "/tf", P.cdr_tf([("odom", "base_link", st_ns, p, T.matrix_to_quat(R))])))
        if k == 62:  # the last cloud arrives before the /tf samples that bracket it: it waits
            script.append(("put", TOPIC, P.cdr_cloud(clouds[3])))
    script += [("put", TOPIC, P.cdr_cloud(c)) for c in clouds[:3]]
    static = P.cdr_tf([("base_link", "lidar", 0, ext[1], T.matrix_to_quat(ext[0]))])
    pub = start_publisher(tmp_path, {"connect": router, "mode": "jazzy", "script": script,
                                     "at_start": [("/tf_static", static)],  # before anyone listens: from the cache
                                     "advertise": [(TOPIC, P.PC2), ("/tf", P.TFM), ("/tf_static", P.TFM)]})
    st = None
    try:
        cfg = source_cfg(router)
        cfg["frames"] = {"fixed": "odom", "tf_wait_ms": 5000}
        st = ru.SourceIngest(cfg)
        tokens = {rz.parse_token(pub.wait_line("MATCHED").split()[1]).topic for _ in range(3)}
        assert tokens == {TOPIC, "/tf", "/tf_static"}
        pub.send("go\n")
        stats = wait_ingest(st, lambda s: s["points_out"] == 160, timeout=120)
        snap = st.ring.snapshot()
        # 81 /tf samples and the cached /tf_static one, on the source's next report
        st.wait_stats(lambda s: st.stage_stats["source"].get("transport_transforms") == 82)
        src = st.stage_stats["source"]
    finally:
        if st is not None:
            st.close()
        pub.close()
    want = {}
    for c in clouds:
        pts = np.column_stack([c.values["x"], c.values["y"], c.values["z"]]).astype(np.float64)
        want[c.stamp_ns] = T.to_fixed(robot, ext, pts, c.stamp_ns + c.values["t"].astype(np.int64))
    order = [clouds[3]] + clouds[:3]
    exp = np.concatenate([want[c.stamp_ns] for c in order])
    assert np.abs(snap.positions - exp).max() < 5e-5, np.abs(snap.positions - exp).max()
    assert stats["drops"] == {} and stats["frames"]["sources"]["source:" + TOPIC]["deskew"].startswith("Ouster t")
    assert src["transport_transforms"] == 82 and src.get("transforms_dropped", 0) == 0


def test_options_are_validated_naming_the_key():
    def load(**opts):
        return load_config({"source": {"transport": "ros2_zenoh", "options": {"topic": TOPIC, **opts}}})

    cfg = load()
    o = cfg.sources[0].options
    assert o["zenoh"]["connect"] == ["tcp/127.0.0.1:7447"] and o["zenoh"]["mode"] == "peer" and o["domain_id"] == 0
    for opts, key, text in [
        ({"topic": "points"}, "options.topic", "starting with '/'"),
        ({"topic": "/a/*"}, "options.topic", "ROS topic name"),
        ({"domain_id": -1}, "options.domain_id", ">= 0"),
        ({"tf_topics": ["tf"]}, "options.tf_topics[0]", "starting with '/'"),
        ({"node_name": "my node"}, "options.node_name", "ROS node name"),
        ({"queue_messages": 0}, "options.queue_messages", ">= 1"),
        ({"zenoh": {"connect": ["tcp/192.0.2.10:7447"]}}, "options.zenoh.connect[0]", "in the clear"),
        ({"zenoh": {"mode": "client", "listen": ["tcp/127.0.0.1:0"]}}, "options.zenoh.connect", "through routers"),
    ]:
        with pytest.raises(ConfigError) as ei:
            load(**opts)
        assert key in str(ei.value) and text in str(ei.value), (opts, str(ei.value))
    insecure = load(zenoh={"connect": ["tcp/192.0.2.10:7447"], "insecure": True})
    assert insecure.sources[0].options["zenoh"]["connect"] == ["tcp/192.0.2.10:7447"]


def test_shipped_config_validates():
    cfg = load_config(str(REPO / "configs" / "ros2-zenoh.yaml"))
    assert cfg.sources[0].transport == "ros2_zenoh"
