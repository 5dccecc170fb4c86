"""A view over a real link (issue 39, item 7): the view server behind a relay that has a
rate and a round-trip time (pointflow/testing/linksim.py: a token-bucket bottleneck with a
router's queue and a propagation delay each way), a WebSocket client that takes frames as
a page does (each acknowledged on arrival), a camera dragged at 60 turns/s.

For each link (``unlimited`` loopback, and ``--rate`` bit/s with ``--rtt`` ms) and each
setting (``serve.adapt_fps: 0``, every moving frame full size at the configured JPEG
quality, the baseline; ``serve.adapt_fps: 20``, frames that fit the link):

* ``moving_fps``  — frames shown per second while the camera moves (after the first second);
* ``bytes``       — bytes per moving frame (median) and the sizes they were sent at;
* ``still``       — after the drag stops: the time to the still frame, its bytes, and whether
  its decoded pixels equal those of the same camera's still drawn for a second client
  connected straight to the server (a full-quality frame): ``pixel_exact``.

    python bench/bench_link.py                 # ~4 min on 2 busy cores
    python bench/bench_link.py --quick         # ~2 min
    python bench/bench_link.py --rate 5e6 --rtt 80

Writes ``bench/results/link.json`` (and ``link.png`` with matplotlib); the load is recorded
before and after (``uptime``).
"""
from __future__ import annotations

import argparse
import io
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

import _harness  # sets XDG_RUNTIME_DIR before pointflow is imported
from _harness import views
from pointflow import Pipeline
from pointflow.testing.linksim import SlowLink

RESULTS = _harness.RESULTS
TOKEN = "bench-link-token-0123456789"


def _config(scene: str, n: int, size, adapt_fps: float) -> dict:
    return {"name": "bench-link",
            "source": {"transport": "file", "name": "cloud", "options": {"path": scene, "realtime": False}},
            "ring": {"max_points": n + 1000}, "cadence": {"target_hz": 60},
            # every point drawn (tier H's budget, 700k, is above them): no frame thins at random,
            # so two draws of one camera are the same pixels and the still can be checked against one
            "policy": {"tier": "H"},
            "render": {"backend": "cpu", "raster": "compute", "size": list(size), "point_size": 2,
                       "color_by": "intensity", "camera": {"mode": "auto"},
                       "output": {"every_n_frames": 10 ** 9}},
            "tracing": {"enabled": False},
            "serve": {"port": 0, "token": TOKEN, "width": int(size[0]), "height": int(size[1]),
                      "adapt_fps": adapt_fps}}


class Client(views.Client):
    """One page's WebSocket through the relay (or straight): frames acknowledged on arrival;
    still frames kept (decoded later)."""

    def __init__(self, port: int, size):
        super().__init__(f"http://127.0.0.1:{port}", token=TOKEN, size=size)

    def ask(self, msg: dict, req: int, timeout: float = 30.0) -> dict:
        self.cmds.put(dict(msg, req=req))
        end = time.monotonic() + timeout
        while req not in self.replies and time.monotonic() < end:
            time.sleep(0.002)
        if req not in self.replies:
            raise RuntimeError(f"no reply to {msg}")
        return self.replies[req]

    def still_after(self, version: int, t0: float, timeout: float = 30.0):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for head, data in reversed(self.stills):
                if head["t"] >= t0 and (head.get("version") or 0) >= version:
                    return head, data
            time.sleep(0.005)
        return None, None

    def close(self) -> None:
        self.stop.set()
        self.join(2)
        try:
            self.ws.close()
        except Exception:  # noqa: BLE001
            pass


def _pixels(data: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


def drag(server_port: int, size, rate, rtt_ms: float, seconds: float, run: int) -> dict:
    """Through a relay: settle, drag for ``seconds`` (60 turns/s), rest, take the still and
    compare it with a full-quality still of the same camera drawn for a direct client."""
    with SlowLink(server_port, rate, rtt_ms / 1e3) as link:
        c = Client(link.port, size)
        try:
            c.ask({"cmd": "fit"}, 1, 60)
            c.still_after(0, 0.0, 60)
            time.sleep(0.5)
            k0 = len(c.frames)
            t0 = time.monotonic()
            i = 0
            sent = []
            while time.monotonic() - t0 < seconds:
                i += 1
                sent.append({"cmd": "orbit", "azimuth_deg": 0.5, "elevation_deg": 0.05 * ((i // 60) % 2 * 2 - 1)})
                c.cmds.put(sent[-1])
                time.sleep(max(0.0, t0 + i / 60.0 - time.monotonic()))
            t_end = time.monotonic()
            last = c.ask({"cmd": "orbit", "azimuth_deg": 0.0}, 2)
            head, data = c.still_after(int(last["version"]), t_end, 60)
            t_still = (head["t"] - t_end) if head else None
            moving = [f for f in c.frames[k0:] if f.get("moving") and t0 + 1.0 <= f["t"] < t_end]
        finally:
            c.close()
        down_bytes = link.counts.get("down", 0)
    out = {"run": run, "link": "unlimited" if not rate else f"{rate / 1e6:g} Mbit/s, {rtt_ms:g} ms RTT",
           "rate_bps": rate, "rtt_ms": rtt_ms, "turns_sent": i,
           "moving_fps": len(moving) / (t_end - t0 - 1.0),
           "moving_bytes_median": float(np.median([f["bytes"] for f in moving])) if moving else None,
           "moving_mbit_s": sum(f["bytes"] for f in moving) * 8 / 1e6 / (t_end - t0 - 1.0),
           "reduce_counts": {str(r): sum(f.get("reduce", 1) == r for f in moving) for r in (1, 2, 4)},
           "quality_median": float(np.median([f.get("quality") or 0 for f in moving])) if moving else None,
           "relay_down_bytes": down_bytes,
           "still_s": t_still, "still_bytes": head["bytes"] if head else None,
           "still_mime": head.get("mime") if head else None}
    if head is None:
        out["pixel_exact"] = False
        return out
    # the reference: a second client straight to the server turns its view by the same
    # messages (the same floats: the same camera) and takes its still
    ref = Client(server_port, size)
    try:
        ref.ask({"cmd": "fit"}, 1, 60)
        ref.still_after(0, 0.0, 60)
        t1 = time.monotonic()
        for j, m in enumerate(sent):
            ref.cmds.put(m)
            if j % 50 == 49:
                time.sleep(0.5)  # under serve.limits.max_messages_per_s
        r = ref.ask({"cmd": "orbit", "azimuth_deg": 0.0}, 2)
        rhead, rdata = ref.still_after(int(r["version"]), t1, 60)
    finally:
        ref.close()
    a, b = _pixels(data), (_pixels(rdata) if rdata is not None else None)
    same = b is not None and a.shape == b.shape
    out["pixel_exact"] = bool(same and np.array_equal(a, b))
    out["pixel_max_diff"] = int(np.abs(a.astype(int) - b.astype(int)).max()) if same else None
    out["pixels_differing"] = int(np.any(a != b, axis=-1).sum()) if same else None
    out["camera_same"] = r.get("camera") == last.get("camera")
    out["still_shape"] = list(a.shape)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=300_000)
    ap.add_argument("--size", default="1280x720")
    ap.add_argument("--rate", type=float, default=10e6, help="the slow link's rate, bit/s")
    ap.add_argument("--rtt", type=float, default=40.0, help="the slow link's round trip, ms")
    ap.add_argument("--seconds", type=float, default=8.0, help="how long each drag lasts")
    ap.add_argument("--target", type=float, default=20.0, help="serve.adapt_fps when adapting")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    runs, seconds = (1, min(args.seconds, 6.0)) if args.quick else (2, args.seconds)
    mach = _harness.machine(command=_harness.command())
    out = {"machine": mach, "uptime_before": mach["uptime_before"], "size": list(size), "points": args.points,
           "client": "websockets client through pointflow.testing.linksim.SlowLink, each frame acknowledged on "
                     "arrival (no browser decode)", "drag": "orbit 0.5 deg at 60 turns/s", "settings": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for name, fps in (("full", 0.0), ("adapt", args.target)):
            d = os.path.join(tmp, name)
            os.makedirs(d)
            rows = []
            with Pipeline.from_dict(_config(views.scene(d, args.points), args.points, size, fps), out_dir=d) as pipe:
                pipe.wait(120, until=lambda: pipe.stats()["stages"]["render"].get("drawn_count", 0) >= args.points)
                pipe.wait(60, until=lambda: pipe.stats()["stages"].get("serve", {}).get("port"))
                port = pipe.stats()["stages"]["serve"]["port"]
                for run in range(runs):  # the two links interleaved
                    for rate, rtt in ((None, 0.0), (args.rate, args.rtt)):
                        row = drag(port, size, rate, rtt, seconds, run)
                        rows.append(row)
                        print(name, json.dumps(row), flush=True)
            out["settings"][name] = {"adapt_fps": fps, "runs": rows, "summary": _summary(rows)}
    _harness.machine_done(mach)
    out["uptime_after"] = mach["uptime_after"]
    slow = out["settings"]["adapt"]["summary"].get("slow", {})
    out["target"] = {"moving_fps_at_slow_link": slow.get("moving_fps_median"), "needed": 15.0,
                     "met": bool(slow.get("moving_fps_median", 0) >= 15.0 and slow.get("pixel_exact_all"))}
    path = _harness.write_result(Path(args.out) if args.out else RESULTS / "link.json", out, 1)
    _chart(out, path.with_suffix(".png"))


def _summary(rows: list[dict]) -> dict:
    out = {}
    for key, sel in (("unlimited", [r for r in rows if not r["rate_bps"]]),
                     ("slow", [r for r in rows if r["rate_bps"]])):
        if not sel:
            continue
        out[key] = {"link": sel[0]["link"], "moving_fps_median": float(np.median([r["moving_fps"] for r in sel])),
                    "moving_bytes_median": float(np.median([r["moving_bytes_median"] or 0 for r in sel])),
                    "still_s_median": float(np.median([r["still_s"] or np.nan for r in sel])),
                    "pixel_exact_all": all(r["pixel_exact"] for r in sel)}
    if "unlimited" in out and "slow" in out and out["unlimited"]["moving_fps_median"]:
        out["slow_over_unlimited_fps"] = out["slow"]["moving_fps_median"] / out["unlimited"]["moving_fps_median"]
    return out


def _chart(out: dict, path: Path) -> None:
    plt = _harness.pyplot()
    if plt is None:
        return
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    names = list(out["settings"])
    links = ["unlimited", "slow"]
    x = np.arange(len(links))
    for i, n in enumerate(names):
        s = out["settings"][n]["summary"]
        ax[0].bar(x + (i - 0.5) * 0.4, [s.get(k, {}).get("moving_fps_median", 0) for k in links], 0.4,
                  label=f"{n} (adapt_fps {out['settings'][n]['adapt_fps']:g})")
        ax[1].bar(x + (i - 0.5) * 0.4, [s.get(k, {}).get("moving_bytes_median", 0) / 1e3 for k in links], 0.4,
                  label=n)
    slow_label = out["settings"][names[0]]["summary"].get("slow", {}).get("link", "slow")
    for a in ax:
        a.set_xticks(x, ["unlimited", slow_label], fontsize=8)
        a.legend(fontsize=8)
    ax[0].axhline(15, color="r", ls="--")
    ax[0].set_ylabel("moving frames/s shown")
    ax[1].set_ylabel("kB per moving frame")
    ax[0].set_title(f"{out['size'][0]}x{out['size'][1]}, {out['points']} points, cpu tier", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


if __name__ == "__main__":
    main()
