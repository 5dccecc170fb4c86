"""The parts of a link that need no second host: config refusals, key files, the encoded
wire format, and the lost-in-transit ledger."""
from __future__ import annotations

import os
import signal
import stat
import subprocess
import sys
import time

import numpy as np
import pytest

from pointflow import wire
from pointflow.chunk import ChunkError, PointChunk
from pointflow.config import ConfigError, load_config
from pointflow.codec import Compressor
from pointflow.remote.keys import create_keypair
from pointflow.remote.options import is_loopback_endpoint
from pointflow.remote.transit import TransitLedger
from pointflow.testing import free_port as _free_port


def _zmq_cfg(**opts):
    return {"source": {"transport": "zmq", "options": {"socket": "pull", **opts}}}


@pytest.mark.parametrize("ep", ["tcp://10.1.2.3:5556", "tcp://*:5556", "tcp://0.0.0.0:5556", "tcp://eth0:5556",
                                "tcp://sensor.local:5556"])
def test_non_loopback_tcp_without_curve_is_refused(ep):
    with pytest.raises(ConfigError) as e:
        load_config(_zmq_cfg(endpoint=ep))
    assert e.value.path == "sources[0].options.endpoint"
    assert "pointflow keys" in str(e.value) and "insecure: true" in str(e.value)
    load_config(_zmq_cfg(endpoint=ep, insecure=True))  # explicit opt-out
    with pytest.raises(ConfigError, match="pointflow keys"):
        load_config({"source": {"transport": "synthetic"}, "send": {"endpoint": ep}})


def test_stage_endpoints_off_loopback_need_insecure():
    cfg = {"source": {"transport": "synthetic"}, "endpoints": {"ingest": "tcp://0.0.0.0:5555"}}
    with pytest.raises(ConfigError) as e:
        load_config(cfg)
    assert e.value.path == "endpoints.ingest" and "pointflow send" in str(e.value)
    cfg["endpoints"]["insecure"] = True
    load_config(cfg)
    load_config({"source": {"transport": "synthetic"}, "endpoints": {"ingest": "tcp://127.0.0.1:5555"}})


@pytest.mark.parametrize("ep", ["tcp://127.0.0.1:5556", "tcp://localhost:1", "tcp://[::1]:5556", "ipc:///tmp/x.sock"])
def test_loopback_needs_no_keys(ep):
    assert is_loopback_endpoint(ep)
    load_config(_zmq_cfg(endpoint=ep))


def test_curve_config_errors_name_the_key(tmp_path):
    pub, sec = create_keypair("a", tmp_path)
    ep = "tcp://10.0.0.1:5556"
    with pytest.raises(ConfigError) as e:
        load_config(_zmq_cfg(endpoint=ep, curve_secret_key=str(tmp_path / "nope.key_secret"), curve_server_key=str(pub)))
    assert e.value.path == "sources[0].options.curve_secret_key" and "does not exist" in str(e.value)
    with pytest.raises(ConfigError) as e:
        load_config(_zmq_cfg(endpoint=ep, curve_secret_key=str(pub), curve_server_key=str(pub)))
    assert "no secret key" in str(e.value)
    with pytest.raises(ConfigError) as e:  # a connecting end needs the server's key
        load_config(_zmq_cfg(endpoint=ep, curve_secret_key=str(sec)))
    assert e.value.path == "sources[0].options.curve_server_key"
    with pytest.raises(ConfigError) as e:  # a binding end needs the authorized folder
        load_config(_zmq_cfg(endpoint=ep, bind=True, curve_secret_key=str(sec)))
    assert e.value.path == "sources[0].options.curve_authorized_keys"
    cfg = load_config(_zmq_cfg(endpoint=ep, bind=True, curve_secret_key="a.key_secret", curve_authorized_keys="."),
                      base_dir=str(tmp_path))
    assert cfg.sources[0].options["curve_secret_key"] == str(sec)  # relative to the config file


def test_keys_cli_writes_a_private_pair(tmp_path):
    run = lambda *a: subprocess.run([sys.executable, "-m", "pointflow.cli", "keys", *a], capture_output=True, text=True)
    p = run("robot1", "--dir", str(tmp_path))
    assert p.returncode == 0, p.stderr
    sec = tmp_path / "robot1.key_secret"
    assert stat.S_IMODE(os.stat(sec).st_mode) == 0o600 and (tmp_path / "robot1.key").is_file()
    p = run("robot1", "--dir", str(tmp_path))
    assert p.returncode == 1 and "already exists" in p.stderr and "Traceback" not in p.stderr


def test_send_needs_a_send_section(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("source: {transport: synthetic}\n")
    p = subprocess.run([sys.executable, "-m", "pointflow.cli", "send", str(f)], capture_output=True, text=True)
    assert p.returncode == 1 and "send:" in p.stderr and "Traceback" not in p.stderr


def _chunk(n=1000, seed=0):
    rng = np.random.default_rng(seed)
    return PointChunk(positions=rng.normal(size=(n, 3)) * 30 + [6.4e5, 4.9e6, 10], source_id="s", seq=4,
                      channels={"intensity": rng.random(n).astype(np.float32),
                                "rgb": rng.integers(0, 255, (n, 3), dtype=np.uint8)})


def test_plain_encoding_is_unchanged():
    c = _chunk()
    c.t_sent_ns = 123
    assert [bytes(f) for f in wire.encode(c)] == [bytes(f) for f in wire.encode(c, link=None, compressor=None)]
    assert b"codec" not in bytes(wire.encode(c)[0])


@pytest.mark.parametrize("codec", [None, "lz4", "zstd"])
@pytest.mark.parametrize("res", [None, 0.001])
def test_encoded_round_trip(codec, res):
    c = _chunk()
    frames = wire.encode(c, link={"epoch": "e", "seq": 0, "sent": 1000},
                         compressor=Compressor(codec) if codec else None, resolution=res)
    d, header = wire.decode_message([bytes(f) for f in frames])
    assert header["link"] == {"epoch": "e", "seq": 0, "sent": 1000}
    assert header.get("codec") == codec
    if res:
        assert header["positions"]["dtype"] == "int32" and header["positions"]["resolution"] == res
        assert np.abs(d.positions - c.positions).max() <= res / 2 * (1 + 1e-6)
    else:
        assert np.array_equal(d.positions, c.positions)
    assert d.positions.dtype == np.float64
    for k in c.channels:
        assert np.array_equal(d.channels[k], c.channels[k])


def test_encoded_defects_are_rejected_with_a_reason():
    c = _chunk(100)
    frames = [bytes(f) for f in wire.encode(c, compressor=Compressor("zstd"))]
    bad = list(frames)
    bad[1] = bad[1][:-5]
    with pytest.raises(ChunkError) as e:
        wire.decode(bad)
    assert e.value.reason in ("bad_compression", "truncated")
    hdr = frames[0].replace(b'"codec":"zstd"', b'"codec":"brotli"')
    with pytest.raises(ChunkError) as e:
        wire.decode([hdr, *frames[1:]])
    assert e.value.reason == "unsupported_codec"
    plain = [bytes(f) for f in wire.encode(c)]
    hdr = plain[0].replace(b'"n":100', b'"shuffle":true,"n":100')
    with pytest.raises(ChunkError) as e:
        wire.decode([hdr, *plain[1:]])
    assert e.value.reason == "bad_header"
    q = [bytes(f) for f in wire.encode(c, resolution=0.01)]
    hdr = q[0].replace(b'"resolution":0.01', b'"resolution":-1')
    with pytest.raises(ChunkError) as e:
        wire.decode([hdr, *q[1:]])
    assert e.value.reason == "bad_header"


def test_too_wide_for_int32_falls_back_to_floats():
    c = PointChunk(positions=np.array([[0.0, 0, 0], [1e7, 0, 0]]))
    d, h = wire.decode_message([bytes(f) for f in wire.encode(c, resolution=0.001)])
    assert h["positions"]["dtype"] == "float64" and np.array_equal(d.positions, c.positions)


def test_ledger_counts_gaps_syncs_and_late_joins():
    t = TransitLedger()
    link = lambda seq, sent, **kw: {"epoch": "A", "seq": seq, "sent": sent, **kw}
    assert t.observe("s", link(0, 100), 100)
    assert t.observe("s", link(1, 200), 100)
    assert t.observe("s", link(4, 500), 100)           # chunks 2 and 3 (200 points) lost
    assert not t.observe("s", link(6, 650, sync=True), 0)  # chunk 5 (50 points) lost at the tail
    c = t.counters()
    assert (c["link_sent"], c["link_received"], c["lost_in_transit"], c["lost_chunks"]) == (650, 300, 350, 3)
    assert not t.observe("s", link(6, 650, sync=True, end=True), 0) and t.ended == {"s"}
    # a receiver that joins late does not count what came before as lost
    late = TransitLedger()
    assert late.observe("s", link(10, 1100), 100)
    assert late.counters()["joined_after"] == 1000 and late.counters()["lost_in_transit"] == 0
    # the sender restarted: a new epoch starts from zero, totals add up
    assert t.observe("s", {"epoch": "B", "seq": 0, "sent": 10}, 10)
    assert t.counters()["link_sent"] == 660 and t.counters()["link_received"] == 310
    with pytest.raises(ChunkError) as e:
        t.observe("s", {"epoch": "B", "seq": 0, "sent": 20}, 10)
    assert e.value.reason == "stale_link_seq"
    with pytest.raises(ChunkError) as e:
        t.observe("s", {"epoch": "B", "seq": "x", "sent": 20}, 10)
    assert e.value.reason == "bad_link"


def test_sender_queue_drops_oldest_data_never_syncs():
    """A link that takes nothing (a PUSH socket with no peer): beyond queue_chunks the oldest
    chunk is dropped and counted; syncs never push data out and never pile up."""
    import logging

    import zmq

    from pointflow.remote.options import SendConfig
    from pointflow.remote.sender import LinkSender
    from pointflow.stage.context import StageCounters

    ctx = zmq.Context()
    sock = ctx.socket(zmq.PUSH)
    sock.setsockopt(zmq.SNDHWM, 1)
    sock.bind("inproc://nobody")
    try:
        counters = StageCounters()
        snd = LinkSender(sock, SendConfig(queue_chunks=2), counters, logging.getLogger("test"))
        for i in range(5):
            snd.add(_chunk(100, seed=i))
            snd.sync()
            snd.sync()
        assert not snd.pump()
        assert counters.drops == {"link_queue_full": 300} and counters.points_out == 0
        assert snd.queued_chunks == 2 and len(snd.queue) == 3  # two newest chunks + one sync
        frames = snd.queue[0][0]
        assert wire.decode_message(frames)[1]["link"]["seq"] == 3  # the oldest kept is chunk 3
        assert wire.decode_message(snd.queue[-1][0])[1]["link"] == {"epoch": snd.epoch, "seq": 5, "sent": 500, "sync": True}
    finally:
        sock.close(0)
        ctx.term()


@pytest.mark.parametrize("client", ["no-curve", "wrong-server-key"])
def test_curve_server_refuses_clients_without_the_right_keys(tmp_path, client):
    """A client without CURVE, or one holding the wrong server key, gets no chunk in; the
    server counts the refused handshake and goes on."""
    import time

    import zmq

    from pointflow.ingest.transports.zmq_transport import ZmqTransport

    srv_pub, srv_sec = create_keypair("server", tmp_path / "s")
    cli_pub, cli_sec = create_keypair("client", tmp_path / "c")
    other_pub, _ = create_keypair("other", tmp_path / "o")
    (tmp_path / "ok").mkdir()
    (tmp_path / "ok" / "client.key").write_text(cli_pub.read_text())
    port = _free_port()
    t = ZmqTransport(ZmqTransport.validate_options(
        {"endpoint": f"tcp://127.0.0.1:{port}", "socket": "pull", "bind": True, "curve_secret_key": str(srv_sec),
         "curve_authorized_keys": str(tmp_path / "ok")}, "t"), "t")
    t.open()
    ctx = zmq.Context()
    push = ctx.socket(zmq.PUSH)
    push.setsockopt(zmq.LINGER, 0)
    if client == "wrong-server-key":
        pub, sec = zmq.auth.load_certificate(str(cli_sec))
        push.curve_publickey, push.curve_secretkey = pub, sec
        push.curve_serverkey = zmq.auth.load_certificate(str(other_pub))[0]
    push.connect(f"tcp://127.0.0.1:{port}")
    try:
        for _ in range(3):
            try:
                wire.send(push, _chunk(100), zmq.NOBLOCK)
            except zmq.Again:
                pass
        got, it, end = 0, t.chunks(), time.monotonic() + 3
        while time.monotonic() < end:
            c = next(it)
            got += c is not None
            t._poll_monitor()
            if t.counters["refused_handshakes"] and time.monotonic() > end - 2:
                break
        assert got == 0
        assert t.counters["refused_handshakes"] >= 1 and t.counters["handshakes"] == 0
    finally:
        push.close(0)
        ctx.term()
        t.close()


def test_stop_waits_for_a_link_mid_reconnect_to_hand_over_the_final_sync():
    """A link a heartbeat dropped just before the stop is mid-reconnect: the sender keeps the
    final sync until the peer is back (here 2.5 s later, past the close's 1.5-s linger that
    lost it before) and the receiver gets it; a link that never had a peer is not waited for."""
    import logging
    import threading
    import time
    import types

    import zmq

    from pointflow.remote.options import SendConfig
    from pointflow.remote.security import LinkSecurity
    from pointflow.remote.sender import LinkSender, hand_over_end
    from pointflow.stage.context import StageCounters

    log = logging.getLogger("test")
    stage = types.SimpleNamespace(log=log, beat=lambda: None)
    ep = f"tcp://127.0.0.1:{_free_port()}"
    ctx = zmq.Context()
    cfg = SendConfig(endpoint=ep, bind=False, socket="push", heartbeat_ivl_s=0.2, heartbeat_timeout_s=1.0,
                     heartbeat_ttl_s=1.0)
    out = ctx.socket(zmq.PUSH)
    out.setsockopt(zmq.LINGER, 1500)
    link = LinkSecurity(ctx, cfg, False, log, 0.1, 0.5)
    link.apply(out)
    out.connect(ep)
    got: list = []
    done = threading.Event()
    threads: list[threading.Thread] = []

    def bind_pull():
        """A PULL on ``ep``: a socket closed a moment ago may still hold the port (ZeroMQ
        closes it in its I/O thread), so bind again until it is free."""
        pull = ctx.socket(zmq.PULL)
        pull.setsockopt(zmq.LINGER, 0)
        deadline = time.monotonic() + 30
        while True:
            try:
                pull.bind(ep)
                return pull
            except zmq.ZMQError:
                if time.monotonic() > deadline:
                    pull.close(0)
                    raise
                time.sleep(0.05)

    def receive(delay: float) -> None:
        """A receiver that binds after ``delay`` and stays until the test is done with it."""
        time.sleep(delay)
        pull = bind_pull()
        try:
            while not done.is_set():
                if pull.poll(50):
                    got.append(wire.decode_message(pull.recv_multipart())[1]["link"])
        finally:
            pull.close()

    try:
        snd = LinkSender(out, cfg, StageCounters(), log)
        first = threading.Thread(target=receive, args=(0,))
        threads.append(first)
        first.start()
        deadline = time.monotonic() + 20
        while not link.counters["handshakes"] and time.monotonic() < deadline:
            link.poll()
            time.sleep(0.02)
        snd.add(_chunk(100, seed=1))
        snd.sync(end=True)
        assert snd.pump()
        assert hand_over_end(stage, snd, link, out, 15.0)  # a peer is there
        deadline = time.monotonic() + 20
        while not (got and got[-1].get("end")) and time.monotonic() < deadline:
            time.sleep(0.02)
        done.set()
        first.join(20)
        assert got and got[-1]["end"], got
        pull = bind_pull()  # a receiver that comes and goes: the link drops
        deadline = time.monotonic() + 20
        while link.counters["handshakes"] < 2 and time.monotonic() < deadline:
            link.poll()
            time.sleep(0.02)
        pull.close()
        while link.counters["peers"] and time.monotonic() < deadline:
            link.poll()
            time.sleep(0.02)
        assert link.counters["peers"] == 0, link.counters
        got.clear()
        done.clear()
        snd.add(_chunk(50, seed=2))
        snd.sync(end=True)
        assert snd.pump()  # into the pipe, no peer to take it
        later = threading.Thread(target=receive, args=(2.5,))
        threads.append(later)
        later.start()
        assert hand_over_end(stage, snd, link, out, 15.0)
        out.close()  # as the stage does: lingers for what ZeroMQ still holds
        deadline = time.monotonic() + 20
        while not (got and got[-1].get("end")) and time.monotonic() < deadline:
            time.sleep(0.02)
        done.set()
        later.join(20)
        assert got and got[-1] == {"epoch": snd.epoch, "seq": 2, "sent": 150, "sync": True, "end": True}, got
    finally:
        done.set()
        for th in threads:
            th.join(40)
        link.close()
        ctx.destroy(linger=0)  # every socket left open by a failed step, so the test ends
    nobody = zmq.Context()
    try:
        pub = nobody.socket(zmq.PUB)
        quiet = LinkSecurity(nobody, cfg, True, log)
        quiet.apply(pub)
        pub.bind(f"tcp://127.0.0.1:{_free_port()}")
        lone = LinkSender(pub, cfg, StageCounters(), log)
        lone.sync(end=True)
        t0 = time.monotonic()
        assert not hand_over_end(stage, lone, quiet, pub, 15.0)
        assert time.monotonic() - t0 < 10  # not the 15-s wait: no peer ever joined
        quiet.close()
        pub.close(0)
    finally:
        nobody.destroy(linger=0)


@pytest.mark.parametrize("socket", ["sub", "pull"])
def test_a_sender_that_stopped_says_what_came_before_this_source_joined(socket, caplog):
    """The viewer's line when a sender stops names the points sent before it joined (they are
    in ``transport_joined_after``, not in the link totals); on a ``sub`` source, with the
    remedy (a pub sender's first chunks go before a subscriber's connection is up). Without a
    late join the line says nothing of it."""
    import logging

    from pointflow.ingest.transports.zmq_transport import ZmqTransport

    def line(first_seq: int) -> str:
        t = ZmqTransport(ZmqTransport.validate_options(
            {"endpoint": "tcp://127.0.0.1:1", "socket": socket, "bind": False}, "t"), "t")
        c = PointChunk(positions=np.zeros((100, 3), np.float32), source_id="lidar")
        link = lambda seq, sent, **kw: {"epoch": "A", "seq": seq, "sent": sent, **kw}  # noqa: E731
        caplog.clear()
        with caplog.at_level(logging.INFO):
            t.parse([bytes(f) for f in wire.encode(c, link=link(first_seq, 100 * (first_seq + 1)))])
            end = PointChunk(positions=np.zeros((0, 3), np.float32), source_id="lidar")
            t.parse([bytes(f) for f in wire.encode(end, link=link(first_seq + 1, 100 * (first_seq + 1),
                                                                   sync=True, end=True))])
        return next(r.getMessage() for r in caplog.records if "stopped: sent" in r.getMessage())

    late = line(5)
    assert "sent 100, received 100, lost in transit 0 point(s); 500 point(s) sent before this source joined" in late
    assert ("send.wait_subscribers" in late) == (socket == "sub"), late
    assert "joined" not in line(0)


def test_a_sender_nobody_joined_does_not_say_it_sent(tmp_path):
    """`pointflow send` with no receiver: ZeroMQ took every point and delivered none, so the
    summary says so (it said "sent N ... MB on the link")."""
    port = _free_port()
    cfg = tmp_path / "s.yaml"
    cfg.write_text("source: {transport: synthetic, name: lidar, options: {scan_hz: 10, points_per_scan: 2000}}\n"
                   f"send: {{endpoint: 'tcp://127.0.0.1:{port}', socket: pub, bind: true}}\n")
    proc = subprocess.run([sys.executable, "-m", "pointflow.cli", "send", str(cfg), "--duration", "2", "-q"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = proc.stdout + proc.stderr
    assert "no receiver joined the link: " in out and "reached nobody" in out, out[-2000:]
    assert "MB on the link" not in out, out[-2000:]


def test_a_sender_that_stops_is_not_a_peer_that_went_away(tmp_path):
    """A viewer whose sender stopped normally: its final sync is said at info ('stopped:
    sent ...'), and the disconnect after it too, not warned of as a peer that went away."""
    port = _free_port()
    (tmp_path / "s.yaml").write_text(
        "source: {transport: synthetic, name: lidar, options: {scan_hz: 10, points_per_scan: 2000}}\n"
        f"send: {{endpoint: 'tcp://127.0.0.1:{port}', socket: pub, bind: true, wait_subscribers: 1}}\n")
    (tmp_path / "v.yaml").write_text(
        f"source: {{transport: zmq, name: robot, options: {{endpoint: 'tcp://127.0.0.1:{port}'}}}}\n"
        "render: {backend: cpu, size: [64, 48]}\n")
    viewer = subprocess.Popen([sys.executable, "-m", "pointflow.cli", "run", "v.yaml", "--duration", "120", "-q",
                               "--out", "out"], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        snd = subprocess.run([sys.executable, "-m", "pointflow.cli", "send", "s.yaml", "--duration", "3", "-q"],
                             cwd=tmp_path, capture_output=True, text=True, timeout=120)
        assert snd.returncode == 0, snd.stderr[-2000:]
        time.sleep(5)  # the viewer reads the final sync, then sees the disconnect
        viewer.send_signal(signal.SIGINT)
    finally:
        _, err = viewer.communicate(timeout=120)
    assert "sender of 'lidar' stopped: sent " in err, err[-3000:]
    assert "went away" not in err and "left on tcp://" in err, err[-3000:]
