"""Picking and save-on-request through the running pipeline (render stage over ZeroMQ,
resolved through the shared-memory ring in float64)."""
from __future__ import annotations

import time

import numpy as np
import pytest
import zmq

from pointflow import Pipeline, wire
from pointflow.chunk import PointChunk, new_trace_id
from pointflow.render.camera import Camera, project_to_pixels

from ..helpers import free_tcp_port

ORIGIN = np.array([640_000.0, 4_900_000.0, 100.0])


def _grid():
    g = np.stack(np.meshgrid(np.arange(-4, 5) * 2.0, np.arange(-4, 5) * 2.0), -1).reshape(-1, 2)
    pts = np.column_stack([g, np.zeros(len(g))]) + ORIGIN + [0.123, 0.456, 0.0]
    return pts


@pytest.mark.parametrize("backend", ["cpu", "wgpu"])
def test_pick_returns_the_point_under_the_cursor(tmp_path, backend):
    if backend == "wgpu":
        from gpu_util import require_adapter

        require_adapter()
    port = free_tcp_port()
    eye, target = ORIGIN + [0, 0, 40.0], ORIGIN.copy()
    cfg = {
        "sources": [{"transport": "zmq", "name": "remote", "external": True}],
        "endpoints": {"ingest": f"tcp://127.0.0.1:{port}"},
        "ring": {"max_points": 1000},
        "render": {"backend": backend, "size": [200, 150], "point_size": 4,
                   "camera": {"mode": "fixed", "position": eye.tolist(), "target": target.tolist(), "up": [0, 1, 0],
                              "near": 1.0, "far": 100.0},
                   "output": {"every_n_frames": 1000}},
        "cadence": {"target_hz": 30},
    }
    pts = _grid()
    ctx = zmq.Context()
    push = ctx.socket(zmq.PUSH)
    push.setsockopt(zmq.LINGER, 0)
    try:
        saved = _pick_session(cfg, tmp_path, push, port, pts, eye, target)
    finally:
        push.close(0)
        ctx.term()
    from PIL import Image

    img = np.asarray(Image.open(saved))
    assert img.shape == (150, 200, 4)
    assert (img[..., :3] != img[0, 0, :3]).any(axis=-1).sum() >= len(pts)


def _pick_session(cfg, tmp_path, push, port, pts, eye, target) -> str:
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path)) as pipe:
        push.connect(f"tcp://127.0.0.1:{port}")
        wire.send(push, PointChunk(positions=pts, channels={"intensity": np.arange(len(pts), dtype=np.float32)},
                                   source_id="remote", trace_id=new_trace_id(), t_sent_ns=time.monotonic_ns()))
        # one cloud, then nothing: the render stage draws it and then only when something changes
        ready = lambda: pipe.stats()["frames"] >= 1 and pipe.stats()["stages"]["render"].get("drawn_count", 0) >= len(pts)
        pipe.wait(60, until=ready)
        assert ready(), "the points never reached the renderer"
        cam = Camera(eye=eye, target=target, up=[0, 1, 0], near=1.0, far=100.0)
        px, py, _, _ = project_to_pixels(pts - ORIGIN, cam.view_proj(200, 150, ORIGIN), 200, 150)
        k = 30
        got = pipe.pick(px[k] + 1.5, py[k] - 1.0)  # a little off the centre, within the radius
        assert got is not None
        np.testing.assert_allclose(got["position"], pts[k], rtol=0, atol=1e-3)
        assert got["channels"]["intensity"] == pytest.approx(float(k))
        # HiDPI: logical coordinates scaled by the pixel ratio
        got2 = pipe.pick(px[k] / 2.0, py[k] / 2.0, pixel_ratio=2.0)
        assert got2 is not None and got2["slot"] == got["slot"]
        assert pipe.pick(2.0, 2.0) is None  # empty corner
        return pipe.save_frame(str(tmp_path / "requested.png"))
