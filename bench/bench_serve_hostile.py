"""Hostile clients against the view server (issue 32): does the render stage, and a good
client beside them, keep its frame rate?

One pipeline (a synthetic lidar streaming 50k points/s into the compiled cpu raster, 320x240,
a view server). Phases of
``--seconds`` each, interleaved ``quiet, hostile, quiet, hostile, ...``:

* ``quiet`` — one good client (the page's protocol: it acks each frame it takes);
* ``hostile`` — the same good client, plus ``--never-read`` clients that open a view and
  never read (nor ack) a frame, ``--liars`` that keep saying "ack" without reading (they
  look like fast viewers until their socket buffer is full), and ``--garbage`` clients per
  tick that connect, send garbage or an oversized message and are thrown out, over and over.

Measured per phase: the render stage's pictures per second (its own ``frames`` plus the
views' frames), and the good client's frames per second. Ratios hostile/quiet, medians over
rounds. The machine is shared: ``uptime`` before and after is written with the results.

    .venv/bin/python bench/bench_serve_hostile.py            # ~2 min
Writes ``bench/results/serve_hostile.json``.
"""
from __future__ import annotations

import argparse
import json
import socket
import statistics
import tempfile
import threading
import time
from pathlib import Path

import _harness as harness

from pointflow import Pipeline
from pointflow.testing.serve import masked_frame, raw_websocket

TOKEN = "bench-token-0123456789abcdef"


def _cfg() -> dict:
    return {"source": {"transport": "synthetic", "name": "lidar", "options": {"scan_hz": 10, "points_per_scan": 5000}},
            "ring": {"max_points": 50000}, "cadence": {"target_hz": 30},
            "render": {"backend": "cpu", "raster": "compute", "size": [320, 240],
                       "output": {"every_n_frames": 1000000}},
            "serve": {"port": 0, "token": TOKEN, "width": 320, "height": 240,
                      "limits": {"send_timeout_s": 5.0, "max_messages_per_s": 100.0}}}


def _render_pictures(pipe) -> int:
    r = pipe.stats()["stages"]["render"]
    return int(r.get("frames", 0)) + int(r.get("view_frames", 0))


class Good(threading.Thread):
    """The page's protocol: read frames, ack each one."""

    def __init__(self, base: str):
        super().__init__(daemon=True)
        from websockets.sync.client import connect

        self.ws = connect(base.replace("http", "ws") + f"/ws?token={TOKEN}",
                          origin=base, max_size=2 ** 24)
        self.ws.pending_legacy_warning = False
        self.frames = 0
        self.stop = False

    def run(self) -> None:
        try:
            while not self.stop:
                try:
                    m = self.ws.recv(timeout=0.5)
                except TimeoutError:
                    continue
                if isinstance(m, bytes):
                    self.frames += 1
                    self.ws.send('{"cmd": "ack"}')
        except Exception:  # noqa: BLE001 - closed at the end
            pass


def _raw(base: str) -> socket.socket:
    return raw_websocket(base, TOKEN, wait_upgrade=False, timeout=0.2)


_masked = masked_frame


class Hostile(threading.Thread):
    def __init__(self, base: str, never_read: int, liars: int, garbage: int):
        super().__init__(daemon=True)
        self.base, self.never_read, self.liars, self.garbage = base, never_read, liars, garbage
        self.stop = False

    def run(self) -> None:
        stuck, silent = [], []
        for _ in range(self.never_read):
            try:
                silent.append(_raw(self.base))
            except OSError:
                pass
        for _ in range(self.liars):
            try:
                stuck.append(_raw(self.base))
            except OSError:
                pass
        junk = [_masked(j) for j in (b"not json", json.dumps({"cmd": "format_disk"}).encode(), b"x" * 40000)]
        ack = _masked(b'{"cmd": "ack"}')  # masked once: the bench's own CPU stays small
        k = 0
        while not self.stop:
            for s in list(stuck):
                try:
                    s.sendall(ack)
                except OSError:
                    stuck.remove(s)
                    try:
                        stuck.append(_raw(self.base))  # thrown out: come back
                    except OSError:
                        pass
            for _ in range(self.garbage):
                try:
                    g = _raw(self.base)
                    g.sendall(junk[k % len(junk)])
                    k += 1
                    g.close()
                except OSError:
                    pass
            time.sleep(0.05)
        for s in stuck + silent:
            s.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--never-read", type=int, default=10)
    ap.add_argument("--liars", type=int, default=0)
    ap.add_argument("--garbage", type=int, default=5)
    ap.add_argument("--out", default=None, help="default bench/results/serve_hostile.json "
                    "(serve_hostile_liars.json with --liars)")
    a = ap.parse_args()
    mach = harness.machine()
    up0 = mach["uptime_before"]
    runs: dict[str, list[dict]] = {"quiet": [], "hostile": []}
    with tempfile.TemporaryDirectory() as d, Pipeline.from_dict(_cfg(), out_dir=d) as pipe:
        pipe.wait(60, until=lambda: pipe.stats()["stages"].get("serve", {}).get("port"))
        base = f"http://127.0.0.1:{pipe.stats()['stages']['serve']['port']}"
        good = Good(base)
        good.start()
        # warm-up: the compiled raster compiles (or loads its cache) on the render stage's first frames
        pipe.wait(120, until=lambda: good.frames >= 20)
        pipe.wait(2)
        for _ in range(a.rounds):
            for phase in ("quiet", "hostile"):
                h = Hostile(base, a.never_read, a.liars, a.garbage) if phase == "hostile" else None
                if h:
                    h.start()
                    pipe.wait(1.0)  # let them connect
                r0, g0, t0 = _render_pictures(pipe), good.frames, time.monotonic()
                pipe.wait(a.seconds)
                r1, g1, t1 = _render_pictures(pipe), good.frames, time.monotonic()
                if h:
                    h.stop = True
                    h.join(10)
                    pipe.wait(1.0)
                runs[phase].append({"render_pictures_per_s": (r1 - r0) / (t1 - t0),
                                    "good_client_fps": (g1 - g0) / (t1 - t0)})
        st = pipe.stats()["stages"]["serve"]
        good.stop = True
        good.ws.close()
    harness.machine_done(mach)
    up1 = mach["uptime_after"]
    med = {p: {k: round(statistics.median(r[k] for r in v), 2) for k in v[0]} for p, v in runs.items()}
    out = {"command": harness.command(), "machine": mach, "uptime_before": up0, "uptime_after": up1,
           "rounds": a.rounds, "seconds": a.seconds,
           "never_read": a.never_read, "liars": a.liars, "garbage_per_tick": a.garbage, "runs": runs, "median": med,
           "ratio_render": round(med["hostile"]["render_pictures_per_s"] / max(1e-9, med["quiet"]["render_pictures_per_s"]), 3),
           "ratio_good_client": round(med["hostile"]["good_client_fps"] / max(1e-9, med["quiet"]["good_client_fps"]), 3),
           "serve_counts": {k: st.get(k) for k in ("bad_messages", "rate_limited", "send_timeouts", "dropped_frames",
                                                   "clients_total", "refused_full")}}
    print(json.dumps({k: out[k] for k in ("median", "ratio_render", "ratio_good_client", "serve_counts")}, indent=1))
    print(up0, up1, sep="\n")
    path = Path(a.out or Path(__file__).parent / "results" / f"serve_hostile{'_liars' if a.liars else ''}.json")
    harness.write_result(path, out, indent=1)


if __name__ == "__main__":
    main()
