"""Frame encoders for the view server (issue 32 item 6): bytes per frame and encode time.

A real picture: the cpu tier draws a synthetic lidar scene (200k points, turbo colours on
a dark background, like the page shows) at each size; each encoder encodes it ``--repeats``
times, interleaved (A B C A B C ...); medians. Also: frames/s of two threads encoding at
once against one (whether the encoder releases the GIL, so the pool scales on 2 cores).

Candidates: simplejpeg (libjpeg-turbo), Pillow JPEG, Pillow PNG at compress_level 1 and 6,
Pillow WebP lossless (method 0),
and OpenCV / imagecodecs / PyTurboJPEG when importable (they are not installed here).
The machine is shared: ``uptime`` before and after is written with the results.

    .venv/bin/python bench/bench_serve_encode.py      # ~1 min
Writes ``bench/results/serve_encode.json``.
"""
from __future__ import annotations

import argparse
import io
import json
import statistics
import threading
import time
from pathlib import Path

import _harness as harness

import numpy as np


def picture(w: int, h: int) -> np.ndarray:
    from pointflow.config import load_config
    from pointflow.render.base import FrameInput  # noqa: F401 - the tier's input type
    from pointflow.render.camera import Camera, project_to_pixels

    rng = np.random.default_rng(3)
    n = 200_000
    ang = rng.uniform(0, 2 * np.pi, n)
    r = rng.uniform(2, 40, n) ** 1.2
    pts = np.column_stack([r * np.cos(ang), r * np.sin(ang), rng.normal(0, 0.3, n) + (r > 30) * 3])
    cam = Camera.fit(pts.min(0), pts.max(0), aspect=w / h)
    px, py, _, ww = project_to_pixels(pts, cam.view_proj(w, h), w, h)
    ok = (ww > 0) & (px >= 0) & (px < w - 1) & (py >= 0) & (py < h - 1)
    from pointflow.render import colormap

    lut = colormap.lut("turbo") if hasattr(colormap, "lut") else None
    img = np.zeros((h, w, 4), np.uint8)
    img[..., :3] = (5, 5, 13)
    img[..., 3] = 255
    t = (r[ok] - r.min()) / np.ptp(r)
    if lut is not None:
        col = (np.asarray(lut)[(t * (len(lut) - 1)).astype(int)][:, :3] * (255 if np.asarray(lut).max() <= 1 else 1))
    else:
        col = np.column_stack([255 * t, 255 * (1 - abs(2 * t - 1)), 255 * (1 - t)])
    for dx in (0, 1):
        for dy in (0, 1):
            img[py[ok].astype(int) + dy, px[ok].astype(int) + dx, :3] = col.astype(np.uint8)
    del load_config
    return img


def encoders() -> dict:
    out = {}
    try:
        import simplejpeg

        out["simplejpeg q80"] = lambda a: simplejpeg.encode_jpeg(a, quality=80, colorspace="RGBA",
                                                                 colorsubsampling="420", fastdct=True)
    except ImportError:
        pass
    from PIL import Image

    def pil(fmt, **kw):
        def enc(a):
            b = io.BytesIO()
            Image.fromarray(a[..., :3]).save(b, format=fmt, **kw)
            return b.getvalue()
        return enc

    out["pillow jpeg q80"] = pil("JPEG", quality=80)
    out["pillow png level 1"] = pil("PNG", compress_level=1)
    out["pillow png level 6"] = pil("PNG", compress_level=6)
    out["pillow webp lossless m0"] = pil("WEBP", lossless=True, quality=0, method=0)
    try:
        import cv2

        out["opencv jpeg q80"] = lambda a: cv2.imencode(".jpg", a[..., 2::-1], [cv2.IMWRITE_JPEG_QUALITY, 80])[1]
        out["opencv png 1"] = lambda a: cv2.imencode(".png", a[..., 2::-1], [cv2.IMWRITE_PNG_COMPRESSION, 1])[1]
    except ImportError:
        pass
    return out


def threads_speedup(enc, img, seconds: float = 1.5) -> float:
    """Frames/s with two threads over frames/s with one."""
    def rate(nthreads: int) -> float:
        count = [0] * nthreads
        stop = time.perf_counter() + seconds

        def work(i):
            while time.perf_counter() < stop:
                enc(img)
                count[i] += 1
        ts = [threading.Thread(target=work, args=(i,)) for i in range(nthreads)]
        for t in ts:
            t.start()
        for t in ts:
            t.join()
        return sum(count) / seconds
    return rate(2) / rate(1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--sizes", default="800x600,1280x720")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "serve_encode.json"))
    a = ap.parse_args()
    mach = harness.machine()
    up0 = mach["uptime_before"]
    encs = encoders()
    res: dict = {}
    for size in a.sizes.split(","):
        w, h = map(int, size.split("x"))
        img = picture(w, h)
        times: dict[str, list[float]] = {k: [] for k in encs}
        nbytes: dict[str, int] = {}
        for k, f in encs.items():
            nbytes[k] = len(f(img))  # warm up (lazy imports) and size
        for _ in range(a.repeats):
            for k, f in encs.items():
                t0 = time.perf_counter()
                f(img)
                times[k].append((time.perf_counter() - t0) * 1e3)
        res[size] = {k: {"encode_ms_p50": round(statistics.median(v), 3), "bytes": nbytes[k],
                         "fps_one_thread": round(1e3 / statistics.median(v), 1),
                         "two_threads_speedup": round(threads_speedup(encs[k], img), 2)}
                     for k, v in times.items()}
        for k, v in res[size].items():
            print(f"{size:9s} {k:20s} {v['encode_ms_p50']:7.2f} ms  {v['bytes'] / 1024:7.1f} KB  "
                  f"2 threads x{v['two_threads_speedup']}")
    harness.machine_done(mach)
    up1 = mach["uptime_after"]
    print(up0, up1, sep="\n")
    harness.write_result(a.out, {"command": harness.command(), "machine": mach,
                                 "uptime_before": up0, "uptime_after": up1,
                                 "repeats": a.repeats, "results": res}, indent=1)


if __name__ == "__main__":
    main()
