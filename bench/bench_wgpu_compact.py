"""Compact positions in the wgpu tier's compute method (issue 41) against its float32 positions
(``POINTFLOW_WGPU_COMPACT=0``), measured in the same run: the scene of ``bench_cpu_threads.py
--cull`` (the autzen tile repeated to N points, 1280x720, 2 px squares, turbo by intensity, 1%
of the ring rewritten per frame, so the encoding's CPU cost is in the frame), three views: the
whole ring, a view of about a tenth of it from closer, and the whole ring from 8x farther.
Frames interleaved in rotating order (frame = render + read_image, which waits for the GPU);
per view the median frame time, the median of the per-round ratios compact / full, the
levels chosen, position bytes read per point and the share of pixels that differ:

    PYTHONPATH=$PWD .venv/bin/python bench/bench_wgpu_compact.py --points 4000000

Writes ``bench/results/wgpu_compact.json``.
"""
from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace
from typing import Any, Optional

import numpy as np

import _harness
from _harness.scenes import H, W, camera_for, tiled_frame
from pointflow.config import RenderConfig


def cameras(world: np.ndarray) -> dict[str, Any]:
    from pointflow.render.camera import Camera
    lo, hi = world.min(0), world.max(0)
    whole = camera_for(world)
    t, asp = np.tan(np.radians(60.0) / 2), W / H
    h = np.sqrt(0.05 * (hi[0] - lo[0]) * (hi[1] - lo[1]) / (4 * asp * t * t))
    c = np.array([lo[0] + 1.2 * asp * t * h, lo[1] + 1.2 * t * h, hi[2]])
    tenth = Camera(eye=c + [0, -1e-3 * h, h], target=c - [0, 0, h], up=[0, 1, 0], fov_deg=60.0,
                   near=0.01 * h, far=4 * h)
    tgt = np.asarray(whole.target, np.float64)
    eye = tgt + 8.0 * (np.asarray(whole.eye, np.float64) - tgt)
    far = Camera(eye=eye, target=tgt, up=whole.up, fov_deg=whole.fov_deg, near=whole.near, far=whole.far * 10)
    return {"whole": whole, "tenth": tenth, "far": far}


def run(n: int, rounds: int) -> dict[str, Any]:
    from pointflow.render.wgpu_tier import WgpuRenderer
    machine = _harness.machine()
    f, world, scene = tiled_frame(n)
    cams = cameras(world)
    del world
    cfg = RenderConfig(size=[W, H], color_by="intensity", colormap="turbo", point_size=2.0, gpu_timestamps=True,
                       backend="wgpu", raster="compute")
    rs = {}
    # every written batch encoded at once (POINTFLOW_WGPU_COMPACT_SETTLE=0), so the frames read
    # compact words from the first and pay for encoding the rewritten 1% (the default settles
    # a batch first: a ring rewritten this fast would stay float32)
    settle = os.environ.get("POINTFLOW_WGPU_COMPACT_SETTLE")
    os.environ["POINTFLOW_WGPU_COMPACT_SETTLE"] = "0"
    for on in ("1", "0"):
        os.environ["POINTFLOW_WGPU_COMPACT"] = on
        rs[on] = WgpuRenderer(replace(cfg), n, ["intensity"])
    del os.environ["POINTFLOW_WGPU_COMPACT"]
    if settle is None:
        del os.environ["POINTFLOW_WGPU_COMPACT_SETTLE"]
    else:
        os.environ["POINTFLOW_WGPU_COMPACT_SETTLE"] = settle
    pairs = [(v, on) for v in cams for on in rs]
    wall: dict[Any, list[float]] = {p: [] for p in pairs}
    gpu: dict[Any, list[float]] = {p: [] for p in pairs}
    up: dict[Any, list[float]] = {p: [] for p in pairs}
    imgs: dict[Any, np.ndarray] = {}
    levels: dict[str, Any] = {}
    for v, on in pairs:
        f.dirty = None
        rs[on].render(f, cams[v])
        rs[on].read_image()
    step, head = max(n // 100, 1), 0
    for i in range(rounds):
        order = pairs[i % len(pairs):] + pairs[:i % len(pairs)]
        for v, on in order:
            a, b = head, min(head + step, n)
            head = b % n
            f.dirty = [(a, b)]
            t0 = time.perf_counter()
            st = rs[on].render(f, cams[v])
            imgs[(v, on)] = rs[on].read_image()
            wall[(v, on)].append((time.perf_counter() - t0) * 1e3)
            up[(v, on)].append(st.timings_ms["upload"])
            if on == "1":
                levels[v] = {"levels": st.extra["compact_levels"],
                             "position_bytes_per_point": st.extra["compact_position_bytes_per_point"]}
            g = rs[on]._gpu_ms.get("gpu_compute")  # (two frames late; the raster passes)
            if g is not None:
                gpu[(v, on)].append(g)
    info = rs["1"].info()
    for r in rs.values():
        r.close()
    views = {}
    for v in cams:
        c, u = wall[(v, "1")], wall[(v, "0")]
        views[v] = {"median_ms": {"compact": float(np.median(c)), "full": float(np.median(u))},
                    "compact_over_full": float(np.median(np.asarray(c) / np.asarray(u))),
                    "median_upload_ms": {"compact": float(np.median(up[(v, "1")])),
                                         "full": float(np.median(up[(v, "0")]))},
                    "median_gpu_compute_ms": {k: (float(np.median(gpu[(v, on)])) if gpu[(v, on)] else None)
                                              for k, on in (("compact", "1"), ("full", "0"))},
                    "diff_fraction": float((imgs[(v, "1")] != imgs[(v, "0")]).any(axis=-1).mean()),
                    **levels[v]}
        print(f"  {v}: compact {views[v]['median_ms']['compact']:.1f} ms, full {views[v]['median_ms']['full']:.1f} ms,"
              f" ratio {views[v]['compact_over_full']:.3f}; levels {levels[v]['levels']},"
              f" {levels[v]['position_bytes_per_point']:.1f} B/pt; pixels differing {views[v]['diff_fraction']:.3%}",
              flush=True)
    return {"points": n, "rounds": rounds, "scene": scene, "size": [W, H], "adapter": info.get("adapter"),
            "chunks": info.get("chunks"), "views": views,
            "machine": _harness.machine_done(machine), "command": _harness.command(),
            "measured_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=4_000_000)
    ap.add_argument("--rounds", type=int, default=12, help="frames per (view, path) pair, interleaved")
    ap.add_argument("--out", default=None, help="default bench/results/wgpu_compact.json")
    a = ap.parse_args(argv)
    _harness.write_result(a.out or _harness.RESULTS / "wgpu_compact.json", run(a.points, a.rounds))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
