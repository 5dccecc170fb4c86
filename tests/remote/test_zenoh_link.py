"""Zenoh links on loopback (docs/remote.md, "The Zenoh engine"): real `pointflow send`
processes with ``engine: zenoh``, real `pointflow run` pipelines (or the real ``zenoh``
transport in a probe process) with the ``zenoh`` source, real Zenoh sessions over TCP.
The namespace topologies (routers, TLS, a slow viewer) are in test_zenoh_topologies.py."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from pointflow.config import load_config
from pointflow.testing import free_port as _port
from pointflow.typed import ConfigError

from .helpers import assert_exact, synthetic_source, wait_for

zenoh = pytest.importorskip("zenoh", reason="eclipse-zenoh comes with the remote extra: pip install 'pointflow[remote]'")
REPO = Path(__file__).resolve().parents[2]


class Loop:
    """Processes of one test on loopback, ended however the test ends."""

    def __init__(self, workdir: Path):
        self.workdir = workdir
        self.procs: list[subprocess.Popen] = []

    def spawn(self, *argv: str, log: str) -> subprocess.Popen:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        with open(self.workdir / log, "w") as f:
            p = subprocess.Popen(list(argv), stdout=f, stderr=subprocess.STDOUT, env=env, cwd=str(self.workdir),
                                 start_new_session=True)
        self.procs.append(p)
        return p

    def pointflow(self, *args: str, log: str) -> subprocess.Popen:
        return self.spawn(sys.executable, "-m", "pointflow.cli", *args, log=log)

    def log(self, name: str) -> str:
        try:
            return (self.workdir / name).read_text()
        except OSError:
            return ""

    def cfg(self, name: str, cfg: dict) -> str:
        path = self.workdir / f"{name}.yaml"
        path.write_text(json.dumps(cfg))
        return str(path)

    def close(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        for p in self.procs:
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()


@pytest.fixture
def loop(tmp_path):
    lp = Loop(tmp_path)
    try:
        yield lp
    finally:
        lp.close()


def zsend_cfg(sources, port: int, key: str = "pftest", **send) -> dict:
    sources = sources if isinstance(sources, list) else [sources]
    return {"sources": sources, "send": {"engine": "zenoh", "key": key, "queue_chunks": 256, "wait_subscribers": 1,
                                         "wait_s": 60, "zenoh": {"listen": [f"tcp/127.0.0.1:{port}"]}, **send}}


def zview_cfg(ports: list[int], key: str = "pftest/**", **opts) -> dict:
    return {"source": {"transport": "zenoh", "name": "link",
                       "options": {"key": key, "zenoh": {"connect": [f"tcp/127.0.0.1:{p}" for p in ports]}, **opts}},
            "ring": {"max_points": 300_000},
            "cadence": {"target_hz": 10},
            "render": {"backend": "cpu", "size": [64, 48], "output": {"dir": None}},
            "tracing": {"enabled": False},
            "supervisor": {"max_restarts": 0}}


def start_view(lp: Loop, cfg: dict, name: str = "recv"):
    p = lp.pointflow("run", lp.cfg(name, cfg), "--duration", "120", "--out", str(lp.workdir / name), "-q",
                     log=f"{name}.log")
    wait_for(lambda: "subscribed zenoh" in lp.log(f"{name}.log"), 60, f"{name} to subscribe", lambda: lp.log(f"{name}.log"))
    return p


def start_send(lp: Loop, cfg: dict, name: str = "send"):
    return lp.pointflow("send", lp.cfg(name, cfg), "--out", str(lp.workdir / name), "-q", log=f"{name}.log")


def stats(lp: Loop, name: str) -> dict:
    return json.loads((lp.workdir / name / "stats.json").read_text())


def finish(lp: Loop, senders: list[tuple[subprocess.Popen, str]], recv, ended: int = 1) -> tuple[list[dict], dict]:
    for p, name in senders:
        assert p.wait(90) == 0, lp.log(f"{name}.log")
    wait_for(lambda: lp.log("recv.log").count("stopped: sent") >= ended, 30, "the senders' final syncs",
             lambda: lp.log("recv.log"))
    recv.send_signal(signal.SIGTERM)
    assert recv.wait(30) == 0, lp.log("recv.log")
    return [stats(lp, name) for _, name in senders], stats(lp, "recv")


def test_exact_counts_send_to_run(loop):
    """`pointflow send` (engine zenoh) to `pointflow run` (zenoh source): every point the
    sensor produced is in the viewer's ring, and every identity of both ends holds."""
    port = _port()
    recv = start_view(loop, zview_cfg([port]))
    send = start_send(loop, zsend_cfg(synthetic_source(), port))
    (snd,), rcv = finish(loop, [(send, "send")], recv)
    assert_exact(snd, rcv)
    ra = rcv["accounting"]
    assert ra["lost_in_transit_by_source"] == {"lidar": 0} and ra["receive_queue_full"] == 0
    assert rcv["stages"]["ingest"]["points_in"] == snd["stages"]["lidar"]["points_out"] > 10_000
    link = rcv["stages"]["link"]
    assert link["transport_senders_lost"] == 0 and link["transport_link_sent:lidar"] == snd["accounting"]["link_sent"]
    assert snd["stages"]["sender"]["link_publishers"] == 1
    assert "sending on zenoh pftest/<source>" in loop.log("send.log")


def _file_source(tmp: Path, n: int = 40_000, chunk_points: int = 5000):
    rng = np.random.default_rng(7)
    xyz = rng.uniform(-80, 80, size=(n, 3)) + [6.4e5, 4.9e6, 120.0]
    np.savez(tmp / "scan.npz", xyz=xyz, intensity=rng.random(n).astype(np.float32))
    return xyz, {"transport": "file", "name": "replay",
                 "options": {"path": str(tmp / "scan.npz"), "mode": "stream", "chunk_points": chunk_points,
                             "realtime": False, "progress": "off"}}


def _probe(lp: Loop, opts: dict, senders: int = 1, hold: float = 0.0):
    p = lp.spawn(sys.executable, str(REPO / "tests/remote/zenoh_probe.py"), json.dumps(opts), str(lp.workdir / "probe"),
                 str(senders), "60", str(hold), log="probe.log")
    wait_for(lambda: "probe: listening" in lp.log("probe.log"), 60, "the probe", lambda: lp.log("probe.log"))
    return p


@pytest.mark.parametrize("codec,resolution", [("none", 0.0), ("lz4", 0.001), ("zstd", 0.01)])
def test_plain_compressed_and_quantised_chunks(loop, codec, resolution):
    """A replay (backpressure: congestion control block) arrives complete and in order: exact
    without quantisation, within half the resolution with it; compressed is smaller."""
    port = _port()
    xyz, src = _file_source(loop.workdir)
    probe = _probe(loop, {"key": "pftest/**", "zenoh": {"connect": [f"tcp/127.0.0.1:{port}"]}})
    send = start_send(loop, zsend_cfg(src, port, compression=codec, quantise=resolution, backpressure=True,
                                      queue_chunks=8))
    assert send.wait(90) == 0, loop.log("send.log")
    assert probe.wait(60) == 0, loop.log("probe.log")
    got = np.load(loop.workdir / "probe.npy")
    counters = json.loads((loop.workdir / "probe.json").read_text())
    assert counters["ended"] == ["replay"] and counters["lost_in_transit"] == 0, counters
    assert counters["receive_queue_full"] == 0 and counters["link_received"] == len(xyz)
    assert got.shape == xyz.shape
    if resolution:
        assert np.abs(got - xyz).max() <= resolution / 2 * (1 + 1e-6)
        assert not np.array_equal(got, xyz)
    else:
        assert np.array_equal(got, xyz)
    snd = stats(loop, "send")
    plain_bytes = xyz.size * 8 + len(xyz) * 4
    if codec != "none":
        assert snd["stages"]["sender"]["link_bytes_out"] < plain_bytes
    else:
        assert snd["stages"]["sender"]["link_bytes_out"] > plain_bytes


def test_two_senders_on_a_wildcard(loop):
    """Two sensor hosts under one prefix, one viewer subscribing pftest/**: each sensor is its
    own source id with its own link accounting, and every point is accounted for: received,
    or counted lost in transit against its source. (A live link publishes with congestion
    control ``drop``: three CI runs out of some thirty lost 7 of one sender's 25 chunks, the
    burst it sends when its subscriber appears, and counted them; the exact-count tests use
    one sender.)"""
    p1, p2 = _port(), _port()
    recv = start_view(loop, zview_cfg([p1, p2]))
    a = start_send(loop, zsend_cfg(synthetic_source("left"), p1, key="pftest/site1"), name="a")
    b = start_send(loop, zsend_cfg(synthetic_source("right"), p2, key="pftest/site2"), name="b")
    (sa, sb), rcv = finish(loop, [(a, "a"), (b, "b")], recv, ended=2)
    ra = rcv["accounting"]
    total = sa["accounting"]["sender_received"] + sb["accounting"]["sender_received"]
    assert ra["link_sent"] == total == ra["link_received"] + ra["lost_in_transit"] and ra["link_balanced"], ra
    lost = ra["lost_in_transit_by_source"]
    assert set(lost) == {"left", "right"} and ra["link_received"] > total // 2, ra
    link = rcv["stages"]["link"]
    assert link["transport_link_sent:left"] == sa["accounting"]["link_sent"] > lost["left"]
    assert link["transport_link_sent:right"] == sb["accounting"]["link_sent"] > lost["right"]
    assert ra["ingest_received"] + ra["sources_dropped"] == ra["link_received"]
    assert "publishing source 'left' on zenoh key pftest/site1/left" in loop.log("a.log")


REPLAY_POINTS = 400_000  # 11 MB: more than loopback's socket buffers, so a held receiver holds the sender


@pytest.mark.parametrize("backpressure", [False, True], ids=["live-drops-counted", "replay-backpressure"])
def test_a_slow_receiver(loop, backpressure):
    """A receiver that takes nothing for a while. Live (default): its bounded queue keeps the
    newest samples, Zenoh's thread never waits, and every dropped chunk's points are counted
    per source as receive_queue_full, so sent = received + lost_in_transit +
    receive_queue_full. With backpressure on both ends (a replay) nothing is dropped: the
    sender waits."""
    port = _port()
    probe = _probe(loop, {"key": "pftest/**", "queue_chunks": 3, "backpressure": backpressure,
                          "zenoh": {"connect": [f"tcp/127.0.0.1:{port}"]}}, hold=6.0)
    if backpressure:
        _, src = _file_source(loop.workdir, n=REPLAY_POINTS)  # more than the sockets' buffers hold
        send = start_send(loop, zsend_cfg(src, port, backpressure=True, queue_chunks=2))
    else:
        send = start_send(loop, zsend_cfg(synthetic_source(scans=10, hz=20), port))
    assert send.wait(90) == 0, loop.log("send.log")
    assert probe.wait(90) == 0, loop.log("probe.log")
    c = json.loads((loop.workdir / "probe.json").read_text())
    snd = stats(loop, "send")
    sent = snd["accounting"]["link_sent"]
    assert c["ended"] == ["replay" if backpressure else "lidar"]
    assert c["link_sent"] == sent == c["link_received"] + c["lost_in_transit"] + c["receive_queue_full"], (c, sent)
    assert len(np.load(loop.workdir / "probe.npy")) == c["link_received"]
    if backpressure:
        assert c["receive_queue_full"] == 0 and c["lost_in_transit"] == 0 and c["link_received"] == sent == REPLAY_POINTS
        # the sender closed its session only once the held receiver had taken its final sync
        assert "1 receiver(s) of pftest/replay took everything" in loop.log("send.log"), loop.log("send.log")
        assert "restarting" not in loop.log("send.log"), loop.log("send.log")
    else:
        assert c["receive_queue_full"] > 0 and c["receive_queue_full_chunks"] > 0, c


def test_a_replay_waits_for_a_late_receiver(loop):
    """The replay's input ends at once, but the sender waits for its subscriber, which comes
    seconds later: the finished source keeps its last chunks and beats while they wait (it
    is not taken for hung and restarted, which would send the file twice), and the sender
    closes only after the receiver took its final sync. Everything arrives, once."""
    port = _port()
    # 400 chunks: more than the source's and the sender's socket queues (64 + 64) hold
    xyz, src = _file_source(loop.workdir, chunk_points=100)
    send = start_send(loop, zsend_cfg(src, port, backpressure=True, queue_chunks=2))
    wait_for(lambda: "publishing source" in loop.log("send.log"), 60, "the sender", lambda: loop.log("send.log"))
    time.sleep(3.0)  # several times supervisor.hung_after_ms (800 ms)
    probe = _probe(loop, {"key": "pftest/**", "backpressure": True, "zenoh": {"connect": [f"tcp/127.0.0.1:{port}"]}})
    assert send.wait(90) == 0, loop.log("send.log")
    assert probe.wait(90) == 0, loop.log("probe.log")
    c = json.loads((loop.workdir / "probe.json").read_text())
    log = loop.log("send.log")
    assert "hung" not in log and "restarting" not in log, log
    assert c["ended"] == ["replay"] and c["link_received"] == len(xyz) == stats(loop, "send")["accounting"]["link_sent"], c
    assert np.array_equal(np.load(loop.workdir / "probe.npy"), xyz)


def test_a_killed_sender_is_noticed(loop):
    """SIGKILL the sender stage mid-stream: its liveliness token goes, the viewer logs the
    lost sender and counts it; the accounting still balances."""
    port = _port()
    recv = start_view(loop, zview_cfg([port]))
    cfg = zsend_cfg(synthetic_source(scans=400, hz=10), port)
    cfg["supervisor"] = {"max_restarts": 0}
    send = start_send(loop, cfg)
    wait_for(lambda: "is alive" in loop.log("recv.log"), 60, "the sender's token", lambda: loop.log("recv.log"))
    time.sleep(2.0)  # some scans and syncs on the way
    pid = int(loop.log("send.log").split("sender[", 1)[1].split("]", 1)[0])
    os.kill(pid, signal.SIGKILL)
    wait_for(lambda: "is gone" in loop.log("recv.log"), 30, "the lost sender", lambda: loop.log("recv.log"))
    send.wait(60)
    recv.send_signal(signal.SIGTERM)
    assert recv.wait(30) == 0, loop.log("recv.log")
    rcv = stats(loop, "recv")
    assert rcv["stages"]["link"]["transport_senders_lost"] == 1
    assert rcv["accounting"]["link_balanced"] and rcv["accounting"]["link_received"] > 0


@pytest.mark.parametrize("send,key,words", [
    ({"engine": "zenoh", "endpoint": "tcp://127.0.0.1:9999"}, "send.endpoint", "zmq engine"),
    ({"engine": "zenoh", "curve_secret_key": "k.key_secret"}, "send.curve_secret_key", "zmq engine"),
    ({"key": "site1"}, "send.key", "engine: zenoh"),
    ({"zenoh": {"listen": ["tcp/127.0.0.1:7448"]}}, "send.zenoh", "engine: zenoh"),
    ({"engine": "zenoh", "key": "pf/*"}, "send.key", "key expression"),
    ({"engine": "zenoh", "key": "pf//a"}, "send.key", "empty chunk"),
    ({"engine": "zenoh", "zenoh": {"listen": ["tcp/0.0.0.0:7448"]}}, "send.zenoh.listen[0]", "in the clear"),
    ({"engine": "zenoh", "zenoh": {"mode": "router"}}, "send.zenoh.mode", "pointflow router"),
    ({"engine": "zenoh", "zenoh": {"mode": "client"}}, "send.zenoh.connect", "routers"),
])
def test_send_config_errors_name_the_key(send, key, words):
    with pytest.raises(ConfigError) as e:
        load_config({"source": {"transport": "synthetic"}, "send": send})
    assert e.value.path == key and words in str(e.value), str(e.value)


@pytest.mark.parametrize("opts,key,words", [
    ({"key": "pf/$x"}, "sources[0].options.key", "key expression"),
    ({"zenoh": {"connect": ["tcp/192.0.2.7:7448"]}}, "sources[0].options.zenoh.connect[0]", "in the clear"),
    ({"zenoh": {"connect": ["tls/192.0.2.7:7448"]}}, "sources[0].options.zenoh.connect[0]", "tls is not set"),
    ({"zenoh": {"mode": "router"}}, "sources[0].options.zenoh.mode", "pointflow router"),
    ({"queue_chunks": 0}, "sources[0].options.queue_chunks", ">= 1"),
])
def test_source_config_errors_name_the_key(opts, key, words):
    with pytest.raises(ConfigError) as e:
        load_config({"source": {"transport": "zenoh", "options": opts}})
    assert e.value.path == key and words in str(e.value), str(e.value)


def test_defaults_are_loopback_and_insecure_is_explicit():
    cfg = load_config({"source": {"transport": "zenoh"}, "send": {"engine": "zenoh"}})
    assert cfg.send.zenoh.listen == ["tcp/127.0.0.1:7448"] and cfg.send.zenoh.connect == []
    assert cfg.sources[0].options["zenoh"]["connect"] == ["tcp/127.0.0.1:7448"]
    assert cfg.sources[0].options["key"] == "pointflow/**"
    ok = load_config({"source": {"transport": "zenoh", "options": {
        "zenoh": {"connect": ["tcp/192.0.2.7:7448"], "insecure": True}}}})
    assert ok.sources[0].options["zenoh"]["connect"] == ["tcp/192.0.2.7:7448"]
    zmq = load_config({"source": {"transport": "synthetic"}, "send": {}})
    assert zmq.send.engine == "zmq" and zmq.send.zenoh is None


def test_single_buffer_framing_round_trip_and_defects():
    """wire.to_single / from_single carry every encoded form (plain, compressed, quantised,
    with a link header) to the same chunk; a body that does not add up is rejected."""
    from pointflow import wire
    from pointflow.chunk import ChunkError, PointChunk
    from pointflow.codec import Compressor

    rng = np.random.default_rng(3)
    c = PointChunk(positions=rng.uniform(-50, 50, (5000, 3)), source_id="lidar",
                   channels={"intensity": rng.random(5000).astype(np.float32)})
    link = {"epoch": "e", "seq": 0, "sent": 5000}
    for kw in ({}, {"link": link}, {"link": link, "compressor": Compressor("lz4")}, {"link": link, "resolution": 0.001}):
        header, body = wire.to_single(wire.encode(c, **kw))
        got, h = wire.decode_message(wire.from_single(header, body))
        assert h.get("link") == kw.get("link") and got.source_id == "lidar"
        tol = 0.0005 if "resolution" in kw else 0.0
        assert np.abs(got.positions - c.positions).max() <= tol * (1 + 1e-6)
        assert np.array_equal(got.channels["intensity"], c.channels["intensity"])
    header, body = wire.to_single(wire.encode(c))
    for bad, reason in ((body[:-1], "truncated"), (body + b"x", "size_mismatch"), (b"\x01", "bad_frame_count"),
                        (b"\xff\xff\xff\x7f" + body[4:], "bad_frame_count")):
        with pytest.raises(ChunkError) as e:
            wire.from_single(header, bad)
        assert e.value.reason == reason


def test_ledger_counts_receiver_drops_apart_from_losses():
    from pointflow.remote.transit import TransitLedger

    t = TransitLedger()
    assert t.observe("a", {"epoch": "e", "seq": 0, "sent": 10}, 10)
    assert not t.observe("a", {"epoch": "e", "seq": 1, "sent": 30}, 20, dropped=True)  # arrived, dropped here
    assert t.observe("a", {"epoch": "e", "seq": 3, "sent": 70}, 15)  # seq 2 (25 points) lost on the way
    assert not t.observe("a", {"epoch": "e", "seq": 4, "sent": 70, "sync": True, "end": True}, 0)
    c = t.counters()
    assert (c["link_sent"], c["link_received"], c["lost_in_transit"], c["receive_queue_full"]) == (70, 25, 25, 20)
