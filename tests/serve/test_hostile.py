"""Hostile clients (issue 32): garbage, binary and oversized messages, a flood, a client
that never reads, 50 clients at once. Each bad client is closed alone and counted; a good
client beside them keeps getting frames; the render stage keeps drawing; nothing leaks.
(No timing asserts: "keeps getting frames" = its count goes up within a generous wait.)"""
from __future__ import annotations

import base64
import json
import os
import socket
import struct
import time

import pytest

from pointflow.testing.serve import masked_frame, raw_websocket

from .conftest import LIMITS
from .helpers import (TOKEN, base_url, closed_with, frames_keep_coming, good_client, is_frame, read_until,
                      serve_stats, ws_connect)


@pytest.fixture
def pipe(hostile_pipe):
    """The package's pipeline (conftest.py), shared with test_attacks.py."""
    return hostile_pipe


def _render_frames(pipe) -> int:
    """Pictures the render stage drew: its own view's and the served views' (its own view
    rests while served views are open)."""
    r = pipe.stats()["stages"]["render"]
    return r.get("frames", 0) + r.get("view_frames", 0)


def _wait_stat(pipe, key, at_least, timeout=20):
    pipe.wait(timeout, until=lambda: serve_stats(pipe).get(key, 0) >= at_least)
    return serve_stats(pipe).get(key, 0)


def test_bad_messages_close_that_client_only(pipe):
    base = base_url(pipe)
    good = good_client(base)
    restarts0 = serve_stats(pipe)["restarts"]
    bad0 = serve_stats(pipe).get("bad_messages", 0)
    f0 = _render_frames(pipe)
    cases = [("text", "this is not json", {1008}), ("text", json.dumps([1, 2]), {1008}),
             ("text", json.dumps({"cmd": "format_disk"}), {1008}), ("text", json.dumps({"cmd": "orbit", "req": "x"}), {1008}),
             ("text", json.dumps({"cmd": "resize", "width": 10 ** 9, "height": 1}), {1008}),
             ("binary", b"\x00" * 100, {1003}), ("text", "x" * (LIMITS["max_message_bytes"] * 4), {1009})]
    for kind, payload, codes in cases:
        ws = ws_connect(base)
        read_until(ws, lambda m: isinstance(m, dict) and m.get("type") == "hello")
        ws.send(payload)
        closed_with(ws, codes)
        ws.close()
    assert _wait_stat(pipe, "bad_messages", bad0 + len(cases)) == bad0 + len(cases)
    frames_keep_coming(good)
    # a control message the render stage refuses is NOT a bad message: an error reply, the client stays
    good.send(json.dumps({"cmd": "zoom", "factor": -1, "req": 7}))
    err = read_until(good, lambda m: isinstance(m, dict) and m.get("type") == "error")
    assert err["req"] == 7 and err["key"] == "zoom.factor"
    frames_keep_coming(good)
    pipe.wait(10, until=lambda: _render_frames(pipe) > f0)  # counts come with heartbeats
    assert _render_frames(pipe) > f0
    good.close()
    assert pipe.stats()["stages"]["serve"]["restarts"] == restarts0
    assert serve_stats(pipe).get("server_errors", 0) == 0 and serve_stats(pipe).get("client_errors", 0) == 0


def _hit_and_run(base: str, payload: bytes, reset: bool) -> None:
    """Connect, send, and leave at once (before the server's answer)."""
    s = socket.create_connection(tuple(base.rsplit("//", 1)[1].split(":")) and
                                 (base.rsplit("//", 1)[1].split(":")[0], int(base.rsplit(":", 1)[1])))
    key = base64.b64encode(os.urandom(16)).decode()
    s.sendall((f"GET /ws?token={TOKEN} HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\n"
               f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n").encode()
              + payload)
    if reset:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # a reset, not a goodbye
    s.close()


def test_clients_that_leave_at_once(pipe):
    base = base_url(pipe)
    good = good_client(base)
    e0 = serve_stats(pipe).get("server_errors", 0)
    for i in range(60):
        _hit_and_run(base, _masked("garbage" * (i % 3)) if i % 2 else b"", reset=i % 4 < 2)
    frames_keep_coming(good)
    pipe.wait(20, until=lambda: serve_stats(pipe).get("clients", 0) == 1)
    assert serve_stats(pipe)["clients"] == 1
    good.close()
    pipe.wait(1.0)
    assert serve_stats(pipe).get("server_errors", 0) == e0, "the web server logged an error for a client"


def test_a_flood_is_cut_off(pipe):
    base = base_url(pipe)
    good = good_client(base)
    r0 = serve_stats(pipe).get("rate_limited", 0)
    ws = ws_connect(base)
    from websockets.exceptions import ConnectionClosed

    with pytest.raises(ConnectionClosed):
        for _ in range(5000):
            ws.send(json.dumps({"cmd": "view_state"}))
        ws.recv(timeout=30)
        ws.recv(timeout=30)
    assert _wait_stat(pipe, "rate_limited", r0 + 1) >= r0 + 1
    frames_keep_coming(good)
    good.close()


def _raw_ws(base: str) -> socket.socket:
    """A WebSocket opened by hand, with a tiny receive buffer, that will never read."""
    return raw_websocket(base, TOKEN)


_masked = masked_frame


def test_a_client_that_never_reads(pipe):
    """It keeps saying "ack" (asking for frames) and never reads one: once its socket is
    full nothing more is written, its acks for frames never written are counted
    (bogus_acks) and give no credit, and it is closed after send_timeout_s; the others go on."""
    base = base_url(pipe)
    good = good_client(base)
    st0 = serve_stats(pipe)
    bad = _raw_ws(base)
    bad.settimeout(0.5)
    c0 = serve_stats(pipe).get("clients_total", 0)
    # big pictures fill the socket buffers sooner
    bad.sendall(_masked(json.dumps({"cmd": "resize", "width": 1024, "height": 768})))
    end = time.monotonic() + 120
    try:
        while time.monotonic() < end:
            try:
                bad.sendall(_masked('{"cmd": "ack"}'))
            except (BlockingIOError, TimeoutError, socket.timeout, OSError):
                pass
            frames_keep_coming(good, 1)
            st = serve_stats(pipe)
            if st.get("send_timeouts", 0) > st0.get("send_timeouts", 0):
                break
            time.sleep(0.05)
    finally:
        bad.close()
    st = serve_stats(pipe)
    assert st["send_timeouts"] > st0.get("send_timeouts", 0), st
    assert st["bogus_acks"] > st0.get("bogus_acks", 0), st
    frames_keep_coming(good)
    good.close()
    pipe.wait(20, until=lambda: serve_stats(pipe).get("clients", 1) == 0)
    assert serve_stats(pipe)["clients"] == 0 and serve_stats(pipe)["clients_total"] >= c0


def _fds(pid: int) -> int:
    return len(os.listdir(f"/proc/{pid}/fd"))


def test_fifty_clients_at_once_and_nothing_leaks(pipe):
    base = base_url(pipe)
    pid = pipe.stats()["stages"]["serve"]["pid"]
    fd0 = _fds(pid)
    restarts0 = (serve_stats(pipe)["restarts"], pipe.stats()["stages"]["render"]["restarts"])
    f0 = _render_frames(pipe)
    clients = []
    try:
        for _ in range(50):
            ws = ws_connect(base)
            read_until(ws, lambda m: isinstance(m, dict) and m.get("type") == "hello")
            clients.append(ws)
        pipe.wait(20, until=lambda: serve_stats(pipe).get("clients", 0) == 50)
        assert serve_stats(pipe)["clients"] == 50
        for ws in clients:  # every one of them gets pictures
            read_until(ws, is_frame, timeout=120)
        pipe.wait(10, until=lambda: _render_frames(pipe) > f0)
        assert _render_frames(pipe) > f0, "the render stage stopped drawing"
        pipe.wait(30, until=lambda: pipe.stats()["stages"]["render"].get("views_open", 0) == 50)
        assert pipe.stats()["stages"]["render"].get("views_open", 0) == 50  # counts come with heartbeats
    finally:
        for ws in clients:
            ws.close()
    pipe.wait(30, until=lambda: serve_stats(pipe).get("clients", 1) == 0
              and pipe.stats()["stages"]["render"].get("views_open", 1) == 0)
    assert serve_stats(pipe)["clients"] == 0
    assert pipe.stats()["stages"]["render"].get("views_open") == 0, "the render stage kept closed views"
    pipe.wait(2)
    assert _fds(pid) <= fd0 + 5, (fd0, _fds(pid))
    f1 = _render_frames(pipe)
    pipe.wait(30, until=lambda: _render_frames(pipe) > f1 + 2)
    assert _render_frames(pipe) > f1 + 2
    assert (serve_stats(pipe)["restarts"], pipe.stats()["stages"]["render"]["restarts"]) == restarts0
