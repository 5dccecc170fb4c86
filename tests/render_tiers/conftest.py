"""Fixtures for the render tier tests: every tier that can run here, and a ring → slab path."""
from __future__ import annotations

import dataclasses
import os
import sys
import uuid
from contextlib import contextmanager

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))
sys.path.insert(0, os.path.dirname(os.path.dirname(__file__)))

os.environ.setdefault("XDG_RUNTIME_DIR", "/tmp/xdg")
os.makedirs(os.environ["XDG_RUNTIME_DIR"], exist_ok=True)

from gpu_util import require_adapter, require_egl  # noqa: E402

#: the wgpu tier runs once per raster method (render.raster); cpu-compute is the cpu tier's
#: compiled raster method (render: {backend: cpu, raster: compute})
TIERS = ["cpu", "cpu-compute", "gl", "wgpu-quads", "wgpu-compute"]


def tier_class(tier: str):
    """The tier's class; missing GPU stacks skip (or fail under POINTFLOW_REQUIRE_GPU=1)."""
    if tier == "cpu":
        from pointflow.render.cpu import CpuRenderer
        return CpuRenderer
    if tier == "cpu-compute":
        from pointflow.render.cpu_compute import CpuComputeRenderer
        return CpuComputeRenderer
    if tier == "gl":
        ctx = require_egl()
        ctx.release()
        from pointflow.render.gl import GlRenderer
        return GlRenderer
    require_adapter()
    from pointflow.render.wgpu_tier import WgpuRenderer
    return WgpuRenderer


@pytest.fixture(params=TIERS)
def tier(request):
    return request.param


@pytest.fixture
def make(tier):
    """make(cfg, capacity, channels) -> renderer of the parametrised tier (closed afterwards)."""
    made = []
    cls = tier_class(tier)

    def _make(cfg, capacity, channels=("intensity",)):
        if tier.startswith("wgpu-") and cfg.raster == "auto":
            cfg = dataclasses.replace(cfg, raster=tier[5:])
        r = cls(cfg, capacity, list(channels))
        made.append(r)
        return r

    yield _make
    for r in made:
        r.close()


@pytest.fixture
def cpu_make():
    from pointflow.render.cpu import CpuRenderer
    return lambda cfg, capacity, channels=("intensity",): CpuRenderer(cfg, capacity, list(channels))


def draw(renderer, frame, camera):
    stats = renderer.render(frame, camera)
    return renderer.read_image(), stats


def diff_fraction(a: np.ndarray, b: np.ndarray) -> float:
    return float((a != b).any(axis=-1).mean())


@contextmanager
def ring_to_frames(ring):
    """Publish the ring through the real slab pair + ZeroMQ handoff and build FrameInputs
    the way the render stage does (``pointflow.render.process.frame_from_slab``)."""
    import time

    import zmq

    from pointflow.render.process import frame_from_slab
    from pointflow.ring import SlabPair, SlabReader, SlabWriter

    zctx = zmq.Context.instance()
    slabs = SlabPair.create(ring.layout)
    tag = uuid.uuid4().hex
    socks = []
    try:
        ready_pull = zctx.socket(zmq.PULL); ready_pull.bind(f"inproc://ready-{tag}")
        ready_push = zctx.socket(zmq.PUSH); ready_push.connect(f"inproc://ready-{tag}")
        rel_pull = zctx.socket(zmq.PULL); rel_pull.bind(f"inproc://rel-{tag}")
        rel_push = zctx.socket(zmq.PUSH); rel_push.connect(f"inproc://rel-{tag}")
        socks = [ready_pull, ready_push, rel_pull, rel_push]
        writer = SlabWriter(ring, slabs, ready_push, rel_pull)
        reader = SlabReader(slabs, ready_pull, rel_push)

        def next_frame():
            reader.release()
            writer.poll_releases()
            h = writer.publish()
            assert h is not None
            got = reader.recv(timeout_ms=2000)
            assert got is not None
            hh, view = got
            return frame_from_slab(hh, view, time.monotonic_ns(), ring.layout.capacity)

        yield next_frame
        reader.release()
    finally:
        for s in socks:
            s.close(0)
        slabs.close()
        slabs.unlink()
