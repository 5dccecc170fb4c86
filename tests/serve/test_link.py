"""A view over a slow link (issue 39): the real view server behind a real relay with a
rate and a round-trip time (pointflow/testing/linksim.py). While the camera is dragged the
frames get smaller (render/view/adapt.py); when it rests, the still is lossless, full size, and
its pixels equal a full-quality still of the same camera drawn for a client connected
straight to the server. Waits on conditions, no timing asserts."""
from __future__ import annotations

import io
import json
import time

import numpy as np
import pytest

from pointflow import Pipeline
from pointflow.testing.linksim import SlowLink

from .helpers import base_url, config, file_source, read_until, scene, ws_connect

W, H = 640, 360


@pytest.fixture(scope="module")
def pipe(tmp_path_factory):
    d = str(tmp_path_factory.mktemp("link"))
    cfg = config(file_source(scene(d)), serve={"width": W, "height": H, "adapt_fps": 20}, size=(W, H))
    with Pipeline.from_dict(cfg, out_dir=d) as p:
        base_url(p)
        p.wait(60, until=lambda: p.stats()["stages"]["render"].get("frames", 0) > 0)
        yield p


def _pixels(data: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


def _is_still(version: int):
    return lambda m: isinstance(m, tuple) and not m[0]["moving"] and (m[0].get("version") or 0) >= version


def _reply(req: int):
    return lambda m: isinstance(m, dict) and m.get("type") == "reply" and m.get("req") == req


def _drag_until_adapted(ws, timeout: float = 120.0) -> tuple[list[dict], int]:
    """Turn the camera ~30 times a second, taking (and acknowledging) frames, until a moving
    frame comes smaller than full (a lower quality or a reduced size); the frames' headers
    and the number of turns."""
    heads: list[dict] = []
    turns = 0
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        ws.send(json.dumps({"cmd": "orbit", "azimuth_deg": 1.0}))
        turns += 1
        t_next = time.monotonic() + 0.033
        while time.monotonic() < t_next:
            try:
                raw = ws.recv(timeout=max(0.001, t_next - time.monotonic()))
            except TimeoutError:
                break
            if isinstance(raw, bytes):
                n = int.from_bytes(raw[:4], "big")
                head = json.loads(raw[4:4 + n])
                heads.append(head)
                ws.send(json.dumps({"cmd": "ack"}))
                if head["moving"] and (head.get("reduce", 1) > 1 or head.get("quality", 80) < 80):
                    return heads, turns
    raise AssertionError(f"no smaller frame while dragging over 1 Mbit/s: {[h.get('bytes') for h in heads][-20:]}")


def test_a_dragged_view_gets_smaller_frames_then_a_lossless_still(pipe):
    direct = base_url(pipe)
    port = int(direct.rsplit(":", 1)[1])
    with SlowLink(port, 1e6, 0.040) as link:
        ws = ws_connect(f"http://127.0.0.1:{link.port}")
        try:
            read_until(ws, lambda m: isinstance(m, dict) and m.get("type") == "hello")
            read_until(ws, lambda m: isinstance(m, tuple))
            heads, turns = _drag_until_adapted(ws)
            ws.send(json.dumps({"cmd": "orbit", "azimuth_deg": 0.0, "req": 7}))
            last = read_until(ws, _reply(7))
            head, data = read_until(ws, _is_still(int(last["version"])), timeout=120)
        finally:
            ws.close()
    moving = [h for h in heads if h["moving"]]
    full = [h["bytes"] for h in moving if h.get("reduce", 1) == 1 and h.get("quality") == 80]
    small = moving[-1]
    assert full, "the first moving frames go at full quality"
    assert small["bytes"] < min(full), (small, full)
    assert small["width"] == W and small["height"] == H  # the view's size: the page draws it there
    # the still: lossless, full size
    assert head["mime"] == "image/png" and head["reduce"] == 1 and head["quality"] == 0
    still = _pixels(data)
    assert still.shape == (H, W, 3)
    # straight to the server, the same turns (the same floats: the same camera): the same pixels
    ws = ws_connect(direct)
    try:
        read_until(ws, lambda m: isinstance(m, tuple))
        for i in range(turns):
            ws.send(json.dumps({"cmd": "orbit", "azimuth_deg": 1.0}))
            if i % 40 == 39:
                read_until(ws, lambda m: isinstance(m, tuple))  # under serve.limits.max_messages_per_s
        ws.send(json.dumps({"cmd": "orbit", "azimuth_deg": 0.0, "req": 8}))
        ref = read_until(ws, _reply(8))
        assert ref["camera"] == last["camera"]
        _, ref_data = read_until(ws, _is_still(int(ref["version"])), timeout=120)
    finally:
        ws.close()
    assert np.array_equal(still, _pixels(ref_data))


def test_the_link_relays_at_its_rate():
    """The relay itself: bytes take len*8/rate of the link plus the delay (a lower bound
    only, so a busy machine cannot fail it)."""
    import socket
    import threading

    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    got = bytearray()

    def serve():
        c, _ = srv.accept()
        c.sendall(b"x" * 200_000)
        c.close()

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    with SlowLink(srv.getsockname()[1], 4e6, 0.1) as link:
        s = socket.create_connection(("127.0.0.1", link.port), timeout=30)
        t0 = time.monotonic()
        while True:
            b = s.recv(65536)
            if not b:
                break
            got += b
        took = time.monotonic() - t0
        s.close()
    srv.close()
    assert bytes(got) == b"x" * 200_000
    assert took >= 200_000 * 8 / 4e6 * 0.9  # 0.4 s of link at least
