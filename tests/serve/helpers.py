"""A pipeline with a view server, and the ways the tests talk to it (real processes,
real sockets, the real browser in test_browser.py)."""
from __future__ import annotations

import contextlib

import json
import os
import struct
import time
import urllib.error
import urllib.request

import numpy as np

TOKEN = "test-token-0123456789abcdef"
W, H = 240, 180


def scene(path: str, known=(1.5, -2.25, 3.0)) -> str:
    """A flat grid of points plus one known point, alone, above the grid's middle."""
    g = np.stack(np.meshgrid(np.arange(-10, 10, 0.25), np.arange(-10, 10, 0.25)), -1).reshape(-1, 2)
    pts = np.vstack([np.column_stack([g, np.zeros(len(g))]), [known]])
    f = os.path.join(path, "scene.npz")
    np.savez(f, x=pts[:, 0], y=pts[:, 1], z=pts[:, 2], intensity=np.arange(len(pts), dtype=np.float32))
    return f


def config(source: dict, *, serve: dict | None = None, size=(W, H), **extra) -> dict:
    cfg = {"source": source, "ring": {"max_points": 20000}, "cadence": {"target_hz": 20},
           "render": {"backend": "cpu", "size": list(size), "point_size": 3, "color_by": "intensity",
                      "output": {"every_n_frames": 100000}},
           "serve": {"port": 0, "token": TOKEN, **(serve or {})}}
    cfg.update(extra)
    return cfg


def file_source(path: str, **options) -> dict:
    return {"transport": "file", "name": "scene", "options": {"path": path, "realtime": False, **options}}


def synthetic_source() -> dict:
    return {"transport": "synthetic", "name": "lidar", "options": {"scan_hz": 10, "points_per_scan": 3000}}


def serve_stats(pipe) -> dict:
    return pipe.stats()["stages"].get("serve", {})


def base_url(pipe, timeout: float = 60.0) -> str:
    """http://127.0.0.1:PORT once the view server listens."""
    pipe.wait(timeout, until=lambda: serve_stats(pipe).get("port"))
    port = serve_stats(pipe).get("port")
    assert port, f"the view server never reported its port: {serve_stats(pipe)}"
    return f"http://127.0.0.1:{port}"


def http_get(url: str, headers: dict | None = None) -> tuple[int, str, dict]:
    """(status, body, headers) without following redirects."""
    class NoRedirect(urllib.request.HTTPRedirectHandler):
        def redirect_request(self, *a, **k):
            return None

    opener = urllib.request.build_opener(NoRedirect)
    req = urllib.request.Request(url, headers=headers or {})
    try:
        with opener.open(req, timeout=20) as r:
            return r.status, r.read().decode(errors="replace"), dict(r.headers)
    except urllib.error.HTTPError as e:
        return e.code, e.read().decode(errors="replace"), dict(e.headers)


_COOKIE_NAMES: dict[str, str] = {}


def cookie_name(base: str) -> str:
    """The name of the token cookie this server sets (per run and port), as a browser
    learns it: from the Set-Cookie of the view: URL's redirect."""
    if base not in _COOKIE_NAMES:
        code, _, headers = http_get(f"{base}/?token={TOKEN}")
        assert code == 303, code
        _COOKIE_NAMES[base] = headers["Set-Cookie"].split("=", 1)[0].split()[-1]
    return _COOKIE_NAMES[base]


def cookie_header(base: str, token: str = TOKEN) -> str:
    return f"{cookie_name(base)}={token}"


def ws_connect(base: str, *, token: str | None = TOKEN, origin: str | None = "same", **kw):
    """A WebSocket to the view server (the websockets sync client), as a page would open it."""
    from websockets.sync.client import connect

    headers = {}
    if token is not None:  # the page's cookie is named per run and port: cookie_header() gives it
        headers["Cookie"] = cookie_header(base, token)
    if origin == "same":
        origin = base
    ws = connect(base.replace("http://", "ws://") + "/ws", additional_headers=headers, origin=origin,
                 max_size=2 ** 24, open_timeout=20, **kw)
    ws.pending_legacy_warning = False  # websockets >= 17.1 asks for `with`; the tests close each one
    return ws


def read_until(ws, pred, timeout: float = 60.0):
    """Messages until ``pred(msg)`` is true for one (returned); frames are decoded to
    (header, image bytes) and acknowledged like the page does."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            raw = ws.recv(timeout=max(0.1, end - time.monotonic()))
        except TimeoutError:
            break
        if isinstance(raw, bytes):
            n = struct.unpack(">I", raw[:4])[0]
            msg = (json.loads(raw[4:4 + n]), raw[4 + n:])
            ws.send(json.dumps({"cmd": "ack"}))
        else:
            msg = json.loads(raw)
        if pred(msg):
            return msg
    raise AssertionError("the expected message did not come")


def is_frame(msg) -> bool:
    return isinstance(msg, tuple)


def good_client(base):
    ws = ws_connect(base)
    read_until(ws, lambda m: isinstance(m, dict) and m.get("type") == "hello")
    read_until(ws, is_frame)
    return ws


def frames_keep_coming(ws, n: int = 2) -> None:
    for _ in range(n):
        read_until(ws, is_frame, timeout=60)


def closed_with(ws, codes) -> int:
    from websockets.exceptions import ConnectionClosed

    end = time.monotonic() + 30
    while time.monotonic() < end:
        try:
            ws.recv(timeout=1)
        except TimeoutError:
            continue
        except ConnectionClosed as exc:
            code = exc.rcvd.code if exc.rcvd is not None else None
            assert code in codes, (code, codes)
            return code
    raise AssertionError("the bad client was not closed")


@contextlib.contextmanager
def scene_pipeline(d: str, **serve):
    """A pipeline replaying :func:`scene` (with its known point) to a view server, started,
    its scene drawn and its page served; ``serve``: options of the ``serve:`` section."""
    from pointflow import Pipeline

    with Pipeline.from_dict(config(file_source(scene(d)), **({"serve": serve} if serve else {})), out_dir=d) as p:
        p.wait(90, until=lambda: p.stats()["stages"]["render"].get("drawn_count", 0) >= 6401)
        base_url(p)
        yield p
