"""The view benches' common parts (bench_views.py, bench_drag.py): a scene file, a pipeline
config with a view server, and a WebSocket client that takes frames as a page does (each
acknowledged on arrival: no decode or paint)."""
from __future__ import annotations

import json
import os
import queue
import struct
import threading
import time

import numpy as np

TOKEN = "bench-views-token-0123456789"


def scene(path: str, n: int) -> str:
    rng = np.random.default_rng(1)
    xy = rng.uniform(-20, 20, (n, 2))
    z = np.sin(xy[:, 0] / 3) * np.cos(xy[:, 1] / 4) * 3 + rng.normal(0, 0.05, n)
    f = os.path.join(path, "cloud.npz")
    np.savez(f, x=xy[:, 0], y=xy[:, 1], z=z, intensity=rng.random(n).astype(np.float32))
    return f


def config(scene: str, n: int, size, backend: str, orbit: float) -> dict:
    render = {"backend": backend, "size": list(size), "point_size": 2, "color_by": "intensity",
              "camera": {"mode": "auto", "orbit_deg_per_s": orbit}, "output": {"every_n_frames": 10 ** 9}}
    if backend == "cpu":
        render["raster"] = "compute"
    return {"name": "bench-views",
            "source": {"transport": "file", "name": "cloud", "options": {"path": scene, "realtime": False}},
            "ring": {"max_points": n + 1000}, "cadence": {"target_hz": 240}, "render": render,
            "tracing": {"enabled": False},
            "serve": {"port": 0, "token": TOKEN, "width": int(size[0]), "height": int(size[1])}}


class Client(threading.Thread):
    """One page's worth of WebSocket: frames acknowledged on arrival, commands from a queue."""

    def __init__(self, base: str, token: str = TOKEN, size=None):
        super().__init__(daemon=True)
        from websockets.sync.client import connect

        self.ws = connect(base.replace("http://", "ws://") + f"/ws?token={token}", origin=base, max_size=2 ** 26,
                          open_timeout=30)
        self.frames: list[dict] = []  # header + t (monotonic s at arrival)
        self.stills: list[tuple[dict, bytes]] = []  # still frames (header, image), decoded by whoever asks
        self.replies: dict[int, dict] = {}
        self.cmds: "queue.SimpleQueue[dict]" = queue.SimpleQueue()
        self.stop = threading.Event()
        if size is not None:  # a view of this size (else the server's default)
            self.cmds.put({"cmd": "resize", "width": int(size[0]), "height": int(size[1])})
        self.start()

    def run(self) -> None:
        while not self.stop.is_set():
            while True:
                try:
                    self.ws.send(json.dumps(self.cmds.get_nowait()))
                except queue.Empty:
                    break
            try:
                raw = self.ws.recv(timeout=0.005)
            except TimeoutError:
                continue
            except Exception:  # noqa: BLE001 - closed
                return
            t = time.monotonic()
            if isinstance(raw, bytes):
                n = struct.unpack(">I", raw[:4])[0]
                head = json.loads(raw[4:4 + n])
                head["t"] = t
                self.frames.append(head)
                if not head.get("moving"):
                    self.stills.append((head, raw[4 + n:]))
                self.ws.send('{"cmd": "ack"}')
            else:
                m = json.loads(raw)
                if m.get("type") == "reply" and m.get("req") is not None:
                    m["t"] = t
                    self.replies[m["req"]] = m

    def turn(self, req: int, azimuth_deg: float = 3.0, timeout: float = 30.0, poll_s: float = 0.0005):
        """Send one ``orbit`` and wait for its reply and the first frame at the reply's
        version: (t0 monotonic s when sent, the reply or {}, that frame or None)."""
        k = len(self.frames)
        t0 = time.monotonic()
        self.cmds.put({"cmd": "orbit", "azimuth_deg": azimuth_deg, "req": req})
        end = t0 + timeout
        while req not in self.replies and time.monotonic() < end:
            time.sleep(poll_s)
        rep = self.replies.get(req, {})
        v, hit = rep.get("version"), None
        while v is not None and hit is None and time.monotonic() < end:
            hit = next((f for f in self.frames[k:] if (f.get("version") or 0) >= v), None)
            time.sleep(poll_s)
        return t0, rep, hit

    def rate(self, t0: float, t1: float) -> float:
        return sum(t0 <= f["t"] < t1 for f in self.frames) / (t1 - t0)

    def close(self) -> None:
        self.stop.set()
        self.join(2)
        try:
            self.ws.close()
        except Exception:  # noqa: BLE001
            pass


def render_stats(pipe) -> dict:
    return pipe.stats()["stages"]["render"]


def base_url(pipe) -> str:
    pipe.wait(60, until=lambda: pipe.stats()["stages"].get("serve", {}).get("port"))
    return f"http://127.0.0.1:{pipe.stats()['stages']['serve']['port']}"
