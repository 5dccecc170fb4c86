"""What a screen-space point size costs the compiled cpu raster (issue 40: one style message
with ``point_size: 4096`` made every frame take 17-18 s at 320x240). The bound on the style
(``render/config.py: MAX_SCREEN_POINT_PX``, 32 px) comes from this table.

    .venv/bin/python bench/bench_point_size.py [--points 50000] [--size 320 240]

Random points in a 20 m cube seen from 30 m; per size the best of 3 frames after a warm-up
frame (each frame draws every point again: ``dirty=[]``, the data already copied). Prints
one line per size and ``uptime`` (the machine is shared).
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import time

import numpy as np

from pointflow.render.base import FrameInput
from pointflow.render.camera import Camera
from pointflow.render.config import RenderConfig
from pointflow.render.cpu_compute import CpuComputeRenderer


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=50000)
    ap.add_argument("--size", type=int, nargs=2, default=[320, 240])
    ap.add_argument("--sizes", type=float, nargs="+", default=[2, 8, 16, 32, 64, 128])
    a = ap.parse_args()
    n = a.points
    pos = ((np.random.default_rng(0).random((n, 3), dtype=np.float32) - 0.5) * 20).astype(np.float32)
    frame = FrameInput(positions=pos, importance=np.zeros(n, np.float32), t_ingest_ms=np.zeros(n), channels={},
                       head=0, size=n, capacity=n, origin=np.zeros(3), now_ms=0.0, dirty=None)
    cam = Camera(eye=[0, -30, 10], target=[0, 0, 0], near=0.1, far=100)
    print(f"load: {os.getloadavg()}; {n} points at {a.size[0]}x{a.size[1]}")
    for ps in a.sizes:
        r = CpuComputeRenderer(RenderConfig(backend="cpu", raster="compute", size=list(a.size), point_size=ps,
                                            color_by="z"), n, [])
        r.render(frame, cam)
        again = dataclasses.replace(frame, dirty=[])
        best = min(_timed(r, again, cam) for _ in range(3))
        print(f"point_size {ps:g} px: {best * 1e3:.1f} ms a frame", flush=True)
        r.close()
    print(f"load: {os.getloadavg()}")


def _timed(r, frame, cam) -> float:
    t = time.perf_counter()
    r.render(frame, cam)
    return time.perf_counter() - t


if __name__ == "__main__":
    main()
