"""Renderer.resize (render/view/hub.py draws views of several sizes with one renderer): a draw
at another size from the data already uploaded (``dirty=[]``) is the picture a renderer of
that size draws, uploads nothing, and switching back finds the first size's picture kept."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from scenes import make_frame, render_cfg, terrain, terrain_camera

from pointflow.render.camera import Camera


def _make(tier: str, cfg, capacity: int, channels):
    if tier == "cpu-reference":
        from pointflow.render.cpu import CpuRenderer

        return CpuRenderer(cfg, capacity, channels)
    if tier == "cpu-compute":
        pytest.importorskip("numba")
        from pointflow.render.cpu_compute import CpuComputeRenderer

        return CpuComputeRenderer(cfg, capacity, channels)
    if tier == "gl":
        from gpu_util import require_egl

        require_egl().release()
        from pointflow.render.gl import GlRenderer

        return GlRenderer(cfg, capacity, channels)
    from gpu_util import require_adapter

    require_adapter()
    from pointflow.render.wgpu_tier import WgpuRenderer

    return WgpuRenderer(cfg, capacity, channels)


@pytest.mark.parametrize("tier", ["cpu-reference", "cpu-compute", "wgpu", "gl"])
def test_resize_draws_the_other_size_from_the_data_uploaded(tier):
    frame = make_frame(terrain(20_000), intensity=np.linspace(0, 1, 20_000).astype(np.float32))
    ch = list(frame.channels)
    cfg = render_cfg(color_by="intensity", point_size=2)
    cam2 = Camera(eye=[-80.0, -60.0, 60.0], target=[0.0, 0.0, 0.0], up=[0.0, 0.0, 1.0], fov_deg=50.0,
                  near=1.0, far=400.0)
    # the picture a renderer of the other size draws (made first: gl contexts are per thread)
    ref = _make(tier, dataclasses.replace(cfg, size=[200, 100]), frame.capacity, ch)
    try:
        ref.render(frame, cam2)
        want = ref.read_image()
    finally:
        ref.close()
    r = _make(tier, cfg, frame.capacity, ch)
    try:
        cam = terrain_camera()
        r.render(frame, cam)
        first = r.read_image()
        assert first.shape == (120, 160, 4)
        assert r.resize(200, 100)
        st = r.render(dataclasses.replace(frame, dirty=[]), cam2)
        got = r.read_image()
        if tier != "gl":  # the tiers that keep the ring upload nothing; gl uploads what it draws
            assert st.uploaded_bytes == 0
        assert got.shape == (100, 200, 4) and np.array_equal(got, want)
        assert r.resize(160, 120)
        assert np.array_equal(r.read_image(), first), "the first size's picture is kept"
    finally:
        r.close()
