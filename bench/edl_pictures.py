"""Pictures of eye-dome lighting (render.edl) for docs/render-wgpu.md and the README: the demo
scene (configs/demo.yaml's synthetic street, 10 scans = 1M points, coloured by intensity) and
the real Autzen airborne tile (../shared/data/autzen_trim.laz, 110k points, rgb), each
rendered by the wgpu tier's compute method with EDL off and on (same frame, same camera),
saved side by side as docs/img/edl_demo.png and docs/img/edl_autzen.png.

    .venv/bin/python bench/edl_pictures.py      # ~1 min on 2 cores (lavapipe)
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

import _harness
from pointflow.config import EdlConfig, RenderConfig
from pointflow.render.base import FrameInput
from pointflow.render.camera import Camera
from pointflow.render.process import write_png
from pointflow.render.wgpu_tier import WgpuRenderer

ROOT = _harness.ROOT
OUT = ROOT / "docs" / "img"
DATA = _harness.DATA
W, H = 800, 450


def frame_of(world: np.ndarray, channels: dict[str, np.ndarray]) -> FrameInput:
    n = len(world)
    org = np.floor(world.min(0))
    ranges = {k: (float(v.min()), float(v.max())) for k, v in channels.items() if v.ndim == 1}
    return FrameInput(positions=(world - org).astype(np.float32), importance=np.ones(n, np.float32),
                      t_ingest_ms=np.zeros(n), channels=channels, head=0, size=n, capacity=n, origin=org,
                      now_ms=0.0, channel_ranges=ranges)


def pair(frame: FrameInput, cam: Camera, cfg: RenderConfig, path: Path) -> None:
    imgs = []
    for on in (False, True):
        r = WgpuRenderer(replace(cfg, raster="compute", edl=EdlConfig(enabled=on)), frame.capacity,
                         list(frame.channels))
        try:
            r.render(frame, cam)
            imgs.append(r.read_image())
        finally:
            r.close()
    gap = np.full((H, 8, 4), 255, np.uint8)
    write_png(str(path), np.concatenate([imgs[0], gap, imgs[1]], axis=1))
    print(f"wrote {path} (left: EDL off, right: EDL on)")


def demo() -> None:
    from pointflow.ingest.transports.synthetic import SyntheticTransport
    src = SyntheticTransport({"scan_hz": 10, "points_per_scan": 100_000})
    chunks = [src.make_chunk(s, k) for s in range(10) for k in range(src.o.chunks_per_scan)]
    world = np.concatenate([np.asarray(c.positions, np.float64) for c in chunks])
    inten = np.concatenate([np.asarray(c.channels["intensity"], np.float32) for c in chunks])
    lo, hi = np.percentile(world, 1, axis=0), np.percentile(world, 99, axis=0)
    cam = Camera.fit(lo, hi, elevation_deg=30, aspect=W / H)
    eye = cam.target + (cam.eye - cam.target) * 0.6
    cam = replace(cam, eye=eye, near=float(np.linalg.norm(eye - cam.target)) * 0.05)
    cfg = RenderConfig(size=[W, H], color_by="intensity", colormap="turbo", point_size=2.0, gpu_timestamps=False)
    pair(frame_of(world, {"intensity": inten}), cam, cfg, OUT / "edl_demo.png")


def autzen() -> None:
    import laspy
    las = laspy.read(str(DATA / "autzen_trim.laz"))
    world = np.column_stack([las.x, las.y, las.z]).astype(np.float64)
    rgb = (np.column_stack([las.red, las.green, las.blue]) / 236.0 * 255.0).clip(0, 255).astype(np.uint8)
    lo, hi = world.min(0), world.max(0)
    cam = Camera.fit(lo, hi, azimuth_deg=-120, elevation_deg=30, aspect=W / H)
    eye = cam.target + (cam.eye - cam.target) * 0.5  # closer: the tile is long and thin
    cam = replace(cam, eye=eye, near=float(np.linalg.norm(eye - cam.target)) * 0.05)
    cfg = RenderConfig(size=[W, H], color_by="rgb", point_size=2.0, background=[1.0, 1.0, 1.0],
                       gpu_timestamps=False)
    pair(frame_of(world, {"rgb": rgb}), cam, cfg, OUT / "edl_autzen.png")


if __name__ == "__main__":
    OUT.mkdir(parents=True, exist_ok=True)
    demo()
    autzen()
