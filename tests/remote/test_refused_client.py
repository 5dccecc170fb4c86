"""A viewer refused by a sender's CURVE server is told so, and counts it (issue 22, item 7),
and its run fails rather than running on empty: real ZeroMQ sockets on loopback, the
sender's server side as `pointflow send` sets it up, and a real `pointflow run`."""
from __future__ import annotations

import logging
import socket
import time

import pytest
import zmq

from pointflow.ingest.transports.base import InputUnreadable
from pointflow.ingest.transports.zmq_transport import ZmqTransport
from pointflow.profiling.report import live_summary
from pointflow.remote.keys import create_keypair
from pointflow.remote.options import SendConfig
from pointflow.remote.security import LinkSecurity
from pointflow.testing import free_port as _free_port


def _curve_pub(srv_sec, authorized):
    """A PUB bound on loopback, the CURVE server side as `pointflow send` sets it up."""
    port = _free_port()
    ctx = zmq.Context()
    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    server = LinkSecurity(ctx, SendConfig(curve_secret_key=str(srv_sec), curve_authorized_keys=str(authorized)),
                          True, logging.getLogger("test.sender"))
    server.apply(pub)
    pub.bind(f"tcp://127.0.0.1:{port}")
    return port, ctx, pub, server


@pytest.mark.parametrize("case", ["key-not-authorized", "wrong-server-key"])
def test_a_refused_viewer_logs_the_refusal_and_counts_it(tmp_path, caplog, case):
    srv_pub, srv_sec = create_keypair("sender", tmp_path / "s")
    cli_pub, cli_sec = create_keypair("viewer", tmp_path / "v")
    other_pub, _ = create_keypair("other", tmp_path / "o")
    (tmp_path / "viewers").mkdir()
    if case == "wrong-server-key":  # authorised, but holding another server's public key
        (tmp_path / "viewers" / "viewer.key").write_text(cli_pub.read_text())
    port, ctx, pub, server = _curve_pub(srv_sec, tmp_path / "viewers")
    viewer = ZmqTransport(ZmqTransport.validate_options(
        {"endpoint": f"tcp://127.0.0.1:{port}", "socket": "sub", "curve_secret_key": str(cli_sec),
         "curve_server_key": str(other_pub if case == "wrong-server-key" else srv_pub)}, "sources[0].options"), "robot")
    caplog.set_level(logging.INFO)
    viewer.open()
    try:
        got, it, end, fatal = 0, viewer.chunks(), time.monotonic() + 15, None
        while time.monotonic() < end and not viewer.counters.get("refused_handshakes"):
            pub.send(b"x")  # nothing gets through a refused link
            try:
                got += next(it) is not None
            except InputUnreadable as exc:
                fatal = str(exc)
                break
            server.poll()
        assert got == 0
        if case == "key-not-authorized" and fatal is None:  # the refusal seen after the loop's last turn
            with pytest.raises(InputUnreadable) as ei:
                next(it)
            fatal = str(ei.value)
        if case == "key-not-authorized":  # ZeroMQ does not retry it: the source fails, saying why
            assert fatal is not None and fatal.startswith("source 'robot': the server at ") \
                and "curve_authorized_keys" in fatal and str(cli_sec) in fatal, fatal
        else:  # a wrong server key is said and retried, not fatal
            assert fatal is None, fatal
        assert viewer.counters["refused_handshakes"] >= 1 and viewer.counters["handshakes"] == 0
        msgs = [r.getMessage() for r in caplog.records if r.name == "pointflow.transport.zmq"]
        if case == "key-not-authorized":
            assert viewer.counters["refused_by_server"] == 1
            assert not any("refused this end's CURVE handshake" in m for m in msgs), "said once: as the error"
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


def test_a_refused_viewers_run_fails_naming_the_key(tmp_path):
    """A `pointflow run` whose zmq source's key the sender refuses exits 2 with the refusal's
    reason, once, and no traceback (it ran to --duration and exited 0)."""
    import subprocess
    import sys

    srv_pub, srv_sec = create_keypair("sender", tmp_path / "s")
    cli_pub, cli_sec = create_keypair("viewer", tmp_path / "v")
    (tmp_path / "viewers").mkdir()  # the viewer's key is not in it
    port, ctx, pub, server = _curve_pub(srv_sec, tmp_path / "viewers")
    cfg = tmp_path / "viewer.yaml"
    cfg.write_text(f"source: {{name: robot, transport: zmq, options: {{endpoint: 'tcp://127.0.0.1:{port}', "
                   f"curve_secret_key: '{cli_sec}', curve_server_key: '{srv_pub}'}}}}\n"
                   "render: {backend: cpu, size: [64, 48]}\n")
    try:
        proc = subprocess.Popen([sys.executable, "-m", "pointflow.cli", "run", str(cfg), "--duration", "120", "-q",
                                 "--out", str(tmp_path / "out")], cwd=tmp_path, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        end = time.monotonic() + 110
        while proc.poll() is None and time.monotonic() < end:
            server.poll()  # the sender's ZAP handler answers in its thread; this reads its monitor
            time.sleep(0.1)
        out, err = proc.communicate(timeout=30)
    finally:
        server.close()
        pub.close(0)
        ctx.term()
    assert proc.returncode == 2, err[-2000:]
    lines = [ln for ln in err.splitlines() if "refused this end's CURVE handshake" in ln]
    assert len(lines) == 1 and str(cli_sec) in lines[0] and "source 'robot'" in lines[0], err[-2000:]
    assert "Traceback" not in err and "restarting" not in err, err[-2000:]
