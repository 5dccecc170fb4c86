"""Each built-in transport against a real peer started by the test."""
import http.server
import json
import os
import socket
import socketserver
import threading
import time

import numpy as np
import pytest
import zmq

from pointflow import wire
from pointflow.chunk import PointChunk
from pointflow.config import ConfigError, load_config
from pointflow.ingest.jsonchunk import chunk_to_json
from pointflow.ingest.quantised import AttributeRange, encode_quantised
from pointflow.ingest.transports import resolve_transport
from pointflow.testing import free_port


def make(name, options, sid="t"):
    cls = resolve_transport(name)
    opts = cls.validate_options(options, "sources[0].options", base_dir=os.getcwd())
    t = cls(opts, sid)
    t.open()
    return t


def collect(t, n_chunks, timeout=20.0):
    out = []
    end = time.monotonic() + timeout
    for c in t.chunks():
        if c is not None:
            out.append(c)
            if len(out) >= n_chunks:
                break
        if time.monotonic() > end:
            break
    return out


def _pts(n, seed=0):
    rng = np.random.default_rng(seed)
    return PointChunk(positions=rng.uniform(-10, 10, (n, 3)),
                      channels={"intensity": rng.uniform(0, 100, n).astype(np.float32)}, source_id="peer", seq=seed)


# ----------------------------------------------------------------------------- synthetic
def test_synthetic_is_deterministic_and_sweeps_a_scene():
    a = make("synthetic", {"realtime": False, "scans": 2, "points_per_scan": 20_000, "seed": 3,
                           "origin": [637000.0, 849000.0, 0.0], "channels": ["intensity", "classification", "beam"]})
    b = make("synthetic", {"realtime": False, "scans": 2, "points_per_scan": 20_000, "seed": 3,
                           "origin": [637000.0, 849000.0, 0.0], "channels": ["intensity", "classification", "beam"]})
    ca, cb = list(a.chunks()), list(b.chunks())
    assert len(ca) == 20  # 2 scans x 10 sectors
    for x, y in zip(ca, cb):
        assert np.array_equal(x.positions, y.positions)
        assert np.array_equal(x.channels["intensity"], y.channels["intensity"])
    pos = np.concatenate([c.positions for c in ca])
    assert pos.dtype == np.float64 and np.isfinite(pos).all()
    assert 0.6 * 40_000 < len(pos) <= 40_000  # sky rays give no return
    local = pos - [637000.0, 849000.0, 0.0]
    assert np.abs(local[:, :2]).max() < 200 and local[:, 2].min() > -0.5
    cls = np.concatenate([c.channels["classification"] for c in ca])
    for code in (2, 5, 6, 11):  # ground, vegetation, buildings, road all seen
        assert (cls == code).sum() > 100
    inten = np.concatenate([c.channels["intensity"] for c in ca])
    assert inten.dtype == np.float32 and inten.min() >= 0 and inten.max() <= 255 and inten.std() > 5
    # each sector covers its own azimuth range around the sensor
    c0 = ca[0].positions - [637000.0, 849000.0, 0.0] - a.sensor_at(0.01)
    assert np.ptp(np.arctan2(c0[:, 1], c0[:, 0])) < 2 * np.pi / 10 + 0.5
    other = make("synthetic", {"realtime": False, "scans": 1, "points_per_scan": 20_000, "seed": 4})
    assert not np.array_equal(next(iter(other.chunks())).channels["intensity"][:100], ca[0].channels["intensity"][:100])


def test_synthetic_cache_scans_replays_and_float32_option():
    t = make("synthetic", {"realtime": False, "scans": 3, "points_per_scan": 5000, "chunks_per_scan": 5,
                           "cache_scans": 1, "positions_dtype": "float32"})
    cs = list(t.chunks())
    assert [c.seq for c in cs] == list(range(15))
    assert all(c.positions.dtype == np.float32 for c in cs)
    for k in range(5):  # scans 1 and 2 replay scan 0
        assert np.array_equal(cs[k].positions, cs[5 + k].positions)
        assert np.array_equal(cs[k].positions, cs[10 + k].positions)
    assert t.counters["rays"] == t.n_az * 32 >= 5000  # cast once (rays per scan: a whole number of firings)


def test_synthetic_options_are_validated():
    with pytest.raises(ConfigError, match=r"sources\[0\]\.options\.scan_hz"):
        load_config({"source": {"transport": "synthetic", "options": {"scan_hz": -1}}})
    with pytest.raises(ConfigError, match=r"sources\[0\]\.options\.channels"):
        load_config({"source": {"transport": "synthetic", "options": {"channels": ["colour"]}}})


# ----------------------------------------------------------------------------- zmq
@pytest.mark.parametrize("kind", ["sub", "pull"])
def test_zmq_transport_receives_wire_and_json_and_rejects_garbage(kind):
    port = free_port()
    ctx = zmq.Context()
    peer = ctx.socket(zmq.PUB if kind == "sub" else zmq.PUSH)
    peer.bind(f"tcp://127.0.0.1:{port}")
    t = make("zmq", {"endpoint": f"tcp://127.0.0.1:{port}", "socket": kind})
    try:
        sent = [_pts(100 + i, i) for i in range(3)]
        got = []
        end = time.monotonic() + 20
        it = t.chunks()
        if kind == "sub":  # slow joiner: a probe (50 points) until the subscription is up, then one round
            up = False
            while not up and time.monotonic() < end:
                wire.send(peer, _pts(50, 9))
                up = any(next(it) is not None for _ in range(20))
        for c in sent:
            wire.send(peer, c)
        peer.send(b"\xff garbage")
        peer.send(chunk_to_json(sent[0]).encode())
        while len(got) < 4 and time.monotonic() < end:
            c = next(it)
            if c is not None and len(c.positions) != 50:  # probes still in flight are not the round
                got.append(c)
        assert len(got) >= 4
        assert np.array_equal(got[0].positions, sent[0].positions)
        assert np.array_equal(got[2].channels["intensity"], sent[2].channels["intensity"])
        assert np.allclose(got[3].positions, sent[0].positions)  # the JSON copy
        assert t.counters["rejected"] >= 1 and t.counters["rejected_bad_json"] >= 1
    finally:
        t.close()
        peer.close(linger=0)
        ctx.term()


def test_zmq_transport_counts_reconnects():
    port = free_port()
    ctx = zmq.Context()
    t = make("zmq", {"endpoint": f"tcp://127.0.0.1:{port}", "socket": "pull", "reconnect_initial_s": 0.05})
    it = t.chunks()
    try:
        for round_ in range(2):
            peer = ctx.socket(zmq.PUSH)
            peer.bind(f"tcp://127.0.0.1:{port}")
            wire.send(peer, _pts(10, round_))
            got = None
            end = time.monotonic() + 20
            while got is None and time.monotonic() < end:
                got = next(it)
            assert got is not None and got.n == 10
            peer.close(linger=0)  # the peer goes away ...
            end = time.monotonic() + 10
            while t.counters["disconnects"] <= round_ and time.monotonic() < end:
                next(it)
        assert t.counters["reconnects"] >= 1 and t.counters["disconnects"] >= 2
    finally:
        t.close()
        ctx.term()


# ----------------------------------------------------------------------------- websocket
class _WsServer:
    """A real websocket server (websockets' sync server) serving scripted messages."""

    def __init__(self, messages, port=None, close_after=True):
        from websockets.sync.server import serve

        self.port = port or free_port()
        self.messages = messages
        self.connections = 0
        self.stop = threading.Event()

        def handler(ws):
            self.connections += 1
            for m in self.messages:
                ws.send(m)
            if not close_after:
                self.stop.wait(30)

        self.server = serve(handler, "127.0.0.1", self.port)
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self):
        self.stop.set()
        self.server.shutdown()
        self.thread.join(5)


def test_websocket_json_columnar_quantised_and_bad_frames():
    schema = [AttributeRange("intensity", 0.0, 1000.0), AttributeRange("t", -1.0, 1.0)]
    rng = np.random.default_rng(0)
    pos = rng.uniform(-20, 30, (500, 3))
    attrs = {"intensity": rng.uniform(0, 1000, 500), "t": rng.uniform(-1, 1, 500)}
    q = encode_quantised(pos, attrs, schema)
    msgs = [
        json.dumps({"points": [{"x": 1, "y": 2, "z": 3, "attributes": {"intensity": 5}}]}),
        json.dumps({"x": [1, 2], "y": [3, 4], "z": [5, 6], "channels": {"intensity": [7, 8]}}),
        q,
        q[:-3],                                   # truncated
        q[:2] + bytes([1]) + q[3:],               # M differs from the schema
        encode_quantised(np.zeros((0, 3)), {}, []) [:2] + bytes([2]) + bytes(17),  # N=0, M=2: empty chunk
        "{not json",
        json.dumps({"points": [{"x": 1, "y": 2}]}),  # wrong shape
    ]
    srv = _WsServer(msgs, close_after=False)
    t = make("websocket", {"url": f"ws://127.0.0.1:{srv.port}",
                           "attributes": [{"name": "intensity", "min": 0, "max": 1000}, {"name": "t", "min": -1, "max": 1}]})
    try:
        got = collect(t, 4)
        assert [c.n for c in got] == [1, 2, 500, 0]
        assert got[0].channels["intensity"][0] == 5
        assert np.array_equal(got[1].positions, [[1, 3, 5], [2, 4, 6]])
        scale = (pos.max(0) - pos.min(0)).max()
        assert np.abs(got[2].positions - pos).max() <= scale / 65535 + 1e-4
        assert np.abs(got[2].channels["intensity"] - attrs["intensity"]).max() <= 1000 / 65535 + 1e-3
        end = time.monotonic() + 5
        while t.counters["rejected"] < 4 and time.monotonic() < end:
            next(t.chunks())
        assert t.counters["rejected_truncated"] == 1 and t.counters["rejected_schema_mismatch"] == 1
        assert t.counters["rejected_bad_json"] == 1 and t.counters["rejected_bad_shape"] == 1
    finally:
        t.close()
        srv.close()


def test_websocket_reconnects_with_backoff():
    port = free_port()
    t = make("websocket", {"url": f"ws://127.0.0.1:{port}", "reconnect_initial_s": 0.05, "reconnect_max_s": 0.2})
    it = t.chunks()
    try:
        for _ in range(5):  # nobody listening yet: retries, no crash
            assert next(it) is None
        srv = _WsServer([json.dumps({"x": [1], "y": [2], "z": [3]})], port=port)
        got = [c for c in (next(it) for _ in range(400)) if c is not None][:1]
        srv.close()  # server goes away after the first message
        srv2 = _WsServer([json.dumps({"x": [4], "y": [5], "z": [6]})], port=port)
        end = time.monotonic() + 20
        while len(got) < 2 and time.monotonic() < end:
            c = next(it)
            if c is not None:
                got.append(c)
        srv2.close()
        assert [c.positions[0, 0] for c in got] == [1, 4]
        assert t.counters["reconnects"] >= 1
    finally:
        t.close()


# ----------------------------------------------------------------------------- sse
class _SseHandler(http.server.BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    events: list = []
    seen_last_id: list = []

    def do_GET(self):
        self.seen_last_id.append(self.headers.get("Last-Event-ID"))
        self.send_response(200)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Transfer-Encoding", "chunked")
        self.end_headers()
        for ev in self.events:
            data = ev.encode()
            # split each event over two HTTP chunks to exercise the incremental parser
            for part in (data[: len(data) // 2], data[len(data) // 2:]):
                if part:
                    self.wfile.write(b"%x\r\n%s\r\n" % (len(part), part))
            self.wfile.flush()
        self.wfile.write(b"0\r\n\r\n")  # end of stream -> client reconnects

    def log_message(self, *a):
        pass


def test_sse_events_multiline_comments_bad_json_and_reconnect():
    c1 = _pts(50, 1)
    js = chunk_to_json(c1)
    half = js.index(", ", len(js) // 2) + 1  # split between tokens: SSE joins lines with a newline
    _SseHandler.events = [
        ": a comment\n\n",
        f"id: 7\nevent: message\ndata: {js[:half]}\ndata: {js[half:]}\n\n",  # multi-line data
        "data: {broken\n\n",
        "event: other\ndata: {\"x\": [1], \"y\": [1], \"z\": [1]}\n\n",
        'data: {"x": [1, 2], "y": [1, 2], "z": [1, 2], "channels": {"intensity": [1]}}\r\n\r\n',
    ]
    _SseHandler.seen_last_id = []
    port = free_port()
    srv = socketserver.ThreadingTCPServer(("127.0.0.1", port), _SseHandler)
    srv.daemon_threads = True
    th = threading.Thread(target=srv.serve_forever, daemon=True)
    th.start()
    t = make("sse", {"url": f"http://127.0.0.1:{port}/stream", "event": "message", "reconnect_initial_s": 0.05})
    try:
        got = collect(t, 2)
        assert np.allclose(got[0].positions, c1.positions)
        assert np.allclose(got[0].channels["intensity"], c1.channels["intensity"])
        assert np.allclose(got[1].positions, c1.positions)  # second connection, same stream again
        assert t.counters["reconnects"] >= 1
        assert t.counters["rejected_bad_json"] >= 1 and t.counters["rejected_length_mismatch"] >= 1
        assert "7" in _SseHandler.seen_last_id  # Last-Event-ID sent on reconnect
    finally:
        t.close()
        srv.shutdown()
        srv.server_close()
