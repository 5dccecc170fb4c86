"""A viewer refused by a sender's CURVE server is told so, and counts it (issue 22, item 7):
real ZeroMQ sockets on loopback, the sender's server side as `pointflow send` sets it up."""
from __future__ import annotations

import logging
import socket
import time

import pytest
import zmq

from pointflow.ingest.transports.zmq_transport import ZmqTransport
from pointflow.profiling.report import live_summary
from pointflow.remote.keys import create_keypair
from pointflow.remote.options import SendConfig
from pointflow.remote.security import LinkSecurity
from pointflow.testing import free_port as _free_port


@pytest.mark.parametrize("case", ["key-not-authorized", "wrong-server-key"])
def test_a_refused_viewer_logs_the_refusal_and_counts_it(tmp_path, caplog, case):
    srv_pub, srv_sec = create_keypair("sender", tmp_path / "s")
    cli_pub, cli_sec = create_keypair("viewer", tmp_path / "v")
    other_pub, _ = create_keypair("other", tmp_path / "o")
    (tmp_path / "viewers").mkdir()
    if case == "wrong-server-key":  # authorised, but holding another server's public key
        (tmp_path / "viewers" / "viewer.key").write_text(cli_pub.read_text())
    port = _free_port()
    ctx = zmq.Context()
    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    server = LinkSecurity(ctx, SendConfig(curve_secret_key=str(srv_sec), curve_authorized_keys=str(tmp_path / "viewers")),
                          True, logging.getLogger("test.sender"))
    server.apply(pub)
    pub.bind(f"tcp://127.0.0.1:{port}")
    viewer = ZmqTransport(ZmqTransport.validate_options(
        {"endpoint": f"tcp://127.0.0.1:{port}", "socket": "sub", "curve_secret_key": str(cli_sec),
         "curve_server_key": str(other_pub if case == "wrong-server-key" else srv_pub)}, "sources[0].options"), "robot")
    caplog.set_level(logging.INFO)
    viewer.open()
    try:
        got, it, end = 0, viewer.chunks(), time.monotonic() + 15
        while time.monotonic() < end and not viewer.counters.get("refused_handshakes"):
            pub.send(b"x")  # nothing gets through a refused link
            got += next(it) is not None
            server.poll()
        assert got == 0
        assert viewer.counters["refused_handshakes"] >= 1 and viewer.counters["handshakes"] == 0
        msgs = [r.getMessage() for r in caplog.records if r.name == "pointflow.transport.zmq"]
        if case == "key-not-authorized":
            assert viewer.counters["refused_by_server"] == 1
            assert any("refused this end's CURVE handshake" in m and str(cli_sec) in m
                       and "curve_authorized_keys" in m for m in msgs), msgs
        else:
            assert viewer.counters["refused_by_server"] == 0
            assert any("CURVE handshake with the server" in m and "curve_server_key" in m and str(other_pub) in m
                       for m in msgs), msgs
        # the refusal's own disconnect is not reported as a peer that went away
        assert not any("went away" in m for m in msgs), msgs
    finally:
        viewer.close()
        server.close()
        pub.close(0)
        ctx.term()


def test_the_live_line_shows_refusals_before_any_data():
    stats = {"elapsed_s": 3.0, "stages": {"robot": {"kind": "source", "points_out": 0,
                                                    "transport_refused_handshakes": 2}}}
    assert "link refused=2" in live_summary(stats)
