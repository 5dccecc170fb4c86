"""Views through the view server (issue 32, Performance): real processes, the real view
server, WebSocket clients that take frames as a page does (decode-free: each frame is
acknowledged on arrival, so a browser's decode and paint are not counted).

Measured, each as a ratio to a baseline taken in the same run (phases interleaved):

* ``one_view``   — frames reaching one client per second vs the render stage's own frame
  rate (the main view drawing with no client), both with the camera orbiting every frame,
  at ``--size`` (default 1280x720) and at 800x600 (target: >= 0.8 of it; at 800x600 >= 25
  frames/s wherever the render stage reaches 30);
* ``drag``       — a turn (``orbit``) sent by a still client to the first frame that shows
  it (its ``version``): p50/p99 vs the render stage's frame time + the encode time;
* ``four_views`` — four clients whose cameras all move: the render stage's total frames/s
  (the four clients' frames) vs one client's alone (target >= 0.8);
* ``bytes``      — bytes per frame while moving (JPEG) and still (PNG), and the link
  speed one view needs at the measured frame rate.

    python bench/bench_views.py                      # ~4-6 min on 2 busy cores
    python bench/bench_views.py --quick              # ~1-2 min
    python bench/bench_views.py --backend wgpu       # the GPU tier (lavapipe here)

Writes ``bench/results/views-<backend>.json`` (and ``.png`` with matplotlib). The machine
is shared: ``uptime`` is recorded before and after.
"""
from __future__ import annotations

import argparse
import json
import os
import random
import tempfile
import time
from pathlib import Path

import numpy as np

import _harness  # sets XDG_RUNTIME_DIR before pointflow is imported
from _harness.views import Client
from _harness.views import base_url as _base_url
from _harness.views import config as _config
from _harness.views import render_stats as _render
from _harness.views import scene as _scene
from pointflow import Pipeline

RESULTS = _harness.RESULTS


def _main_fps(pipe, seconds: float) -> float:
    a = _render(pipe)["frames"]
    t0 = time.monotonic()
    time.sleep(seconds)
    return (_render(pipe)["frames"] - a) / (time.monotonic() - t0)


def _clients_fps(base: str, k: int, seconds: float) -> tuple[float, list[float]]:
    cl = [Client(base) for _ in range(k)]
    try:
        time.sleep(1.0)  # open, first frames
        t0 = time.monotonic()
        time.sleep(seconds)
        t1 = time.monotonic()
        rates = [c.rate(t0, t1) for c in cl]
        return sum(rates), rates
    finally:
        for c in cl:
            c.close()
        time.sleep(0.8)  # the views close; main draws again


def one_view(tmp: str, n: int, size, backend: str, phases: int, phase_s: float) -> dict:
    """Interleaved: render stage alone (main orbiting) vs one client (its view orbiting)."""
    cfg = _config(_scene(tmp, n), n, size, backend, orbit=20.0)
    with Pipeline.from_dict(cfg, out_dir=tmp) as pipe:
        pipe.wait(120, until=lambda: _render(pipe).get("drawn_count", 0) >= n)
        base = _base_url(pipe)
        alone, client, bytes_moving, frame_ms, enc_ms = [], [], [], [], []
        _main_fps(pipe, 1.0)  # warm
        for _ in range(phases):
            alone.append(_main_fps(pipe, phase_s))
            c = Client(base)
            try:
                time.sleep(1.0)
                t0 = time.monotonic()
                time.sleep(phase_s)
                client.append(c.rate(t0, time.monotonic()))
                fr = [f for f in c.frames if f.get("moving")]
                bytes_moving += [f["bytes"] for f in fr]
                frame_ms += [f["frame_ms"] for f in fr if f.get("frame_ms") is not None]
                enc_ms += [f["encode_ms"] for f in fr]
            finally:
                c.close()
            time.sleep(0.8)
    a, c = float(np.median(alone)), float(np.median(client))
    return {"size": list(size), "points": n, "render_alone_fps": alone, "client_fps": client,
            "render_alone_fps_median": a, "client_fps_median": c, "ratio": c / a if a else None,
            "jpeg_bytes_median": float(np.median(bytes_moving)) if bytes_moving else None,
            "view_frame_ms_median": float(np.median(frame_ms)) if frame_ms else None,
            "encode_ms_median": float(np.median(enc_ms)) if enc_ms else None}


def drag(tmp: str, n: int, size, backend: str, repeats: int) -> dict:
    """A still view; ``orbit`` 3 deg; time to the first frame at the reply's version."""
    cfg = _config(_scene(tmp, n), n, size, backend, orbit=0.0)
    lat, frame_ms, enc_ms, png_bytes, jpeg_bytes = [], [], [], [], []
    with Pipeline.from_dict(cfg, out_dir=tmp) as pipe:
        pipe.wait(120, until=lambda: _render(pipe).get("drawn_count", 0) >= n)
        c = Client(_base_url(pipe))
        try:
            time.sleep(1.5)
            for i in range(repeats):
                k = len(c.frames)
                t0, _, hit = c.turn(1000 + i, poll_s=0.001)
                if hit is None:
                    continue
                lat.append((hit["t"] - t0) * 1e3)
                frame_ms.append(hit.get("frame_ms") or 0.0)
                enc_ms.append(hit["encode_ms"])
                jpeg_bytes.append(hit["bytes"]) if hit.get("moving") else png_bytes.append(hit["bytes"])
                time.sleep(random.uniform(0.35, 0.6))  # it settles: the still (PNG) frame comes
                png_bytes += [f["bytes"] for f in c.frames[k:] if not f.get("moving") and f is not hit]
        finally:
            c.close()
    lat_a = np.asarray(lat)
    fm, em = float(np.median(frame_ms)), float(np.median(enc_ms))
    return {"size": list(size), "points": n, "turns": len(lat), "latency_ms": lat,
            "p50_ms": float(np.percentile(lat_a, 50)), "p99_ms": float(np.percentile(lat_a, 99)),
            "view_frame_ms_median": fm, "encode_ms_median": em, "budget_ms": 2 * fm + em,
            "png_bytes_median": float(np.median(png_bytes)) if png_bytes else None,
            "jpeg_bytes_median_first_frames": float(np.median(jpeg_bytes)) if jpeg_bytes else None}


def four_views(tmp: str, n: int, size, backend: str, phases: int, phase_s: float) -> dict:
    cfg = _config(_scene(tmp, n), n, size, backend, orbit=20.0)
    one, four, each = [], [], []
    with Pipeline.from_dict(cfg, out_dir=tmp) as pipe:
        pipe.wait(120, until=lambda: _render(pipe).get("drawn_count", 0) >= n)
        base = _base_url(pipe)
        for _ in range(phases):
            one.append(_clients_fps(base, 1, phase_s)[0])
            tot, rates = _clients_fps(base, 4, phase_s)
            four.append(tot)
            each.append(rates)
    o, f = float(np.median(one)), float(np.median(four))
    return {"size": list(size), "points": n, "one_view_fps": one, "four_views_total_fps": four,
            "four_views_each_fps": each, "ratio": f / o if o else None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="cpu", choices=["cpu", "wgpu"])
    ap.add_argument("--points", type=int, default=300_000)
    ap.add_argument("--size", default="1280x720")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    phases, phase_s, repeats = (2, 3.0, 20) if args.quick else (4, 5.0, 60)
    mach = _harness.machine(command=_harness.command())
    out = {"backend": args.backend, "machine": mach, "uptime_before": mach["uptime_before"], "client": "websockets client, each frame acknowledged on arrival "
           "(no browser decode or paint)"}
    with tempfile.TemporaryDirectory() as tmp:
        for key, fn in (("one_view", lambda d: one_view(d, args.points, size, args.backend, phases, phase_s)),
                        ("one_view_800x600", lambda d: one_view(d, args.points, (800, 600), args.backend, phases,
                                                                phase_s)),
                        ("drag", lambda d: drag(d, args.points, (800, 600), args.backend, repeats)),
                        ("four_views", lambda d: four_views(d, args.points, (800, 600), args.backend, phases,
                                                            phase_s))):
            d = os.path.join(tmp, key)
            os.makedirs(d)
            t = time.monotonic()
            out[key] = fn(d)
            out[key]["seconds"] = round(time.monotonic() - t, 1)
            print(key, json.dumps({k: v for k, v in out[key].items() if not isinstance(v, list)}), flush=True)
    _harness.machine_done(mach)
    out["uptime_after"] = mach["uptime_after"]
    ov, dr = out["one_view"], out["drag"]
    fps = ov["client_fps_median"]
    jb = ov["jpeg_bytes_median"] or 0.0
    out["bytes"] = {"moving_jpeg_bytes": jb, "still_png_bytes": dr["png_bytes_median"],
                    "link_mbit_s_at_client_fps": jb * fps * 8 / 1e6,
                    "link_mbit_s_at_30fps": jb * 30 * 8 / 1e6}
    path = _harness.write_result(Path(args.out) if args.out else RESULTS / f"views-{args.backend}.json", out, 1)
    _chart(out, path.with_suffix(".png"))


def _chart(out: dict, path: Path) -> None:
    plt = _harness.pyplot()
    if plt is None:
        return
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    ov, o8, fv = out["one_view"], out["one_view_800x600"], out["four_views"]
    labels = [f"{ov['size'][0]}x{ov['size'][1]}\nalone / 1 client", "800x600\nalone / 1 client",
              "800x600\n1 client / 4 clients"]
    a = [ov["render_alone_fps_median"], o8["render_alone_fps_median"], float(np.median(fv["one_view_fps"]))]
    b = [ov["client_fps_median"], o8["client_fps_median"], float(np.median(fv["four_views_total_fps"]))]
    x = np.arange(3)
    ax[0].bar(x - 0.2, a, 0.4, label="baseline")
    ax[0].bar(x + 0.2, b, 0.4, label="measured")
    ax[0].set_xticks(x, labels, fontsize=8)
    ax[0].set_ylabel("frames/s")
    ax[0].legend(fontsize=8)
    ax[0].set_title(f"views, {out['backend']} tier", fontsize=9)
    lat = np.sort(out["drag"]["latency_ms"])
    ax[1].plot(lat, np.linspace(0, 1, lat.size))
    ax[1].axvline(out["drag"]["budget_ms"], color="r", ls="--", label="2 frames + encode")
    ax[1].set_xlabel("drag to first frame (ms)")
    ax[1].set_ylabel("fraction")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


if __name__ == "__main__":
    main()
