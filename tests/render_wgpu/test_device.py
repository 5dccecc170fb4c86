"""Adapter selection, failure as RenderError, capacity caps, dirty-range bookkeeping, gpu_util."""
import numpy as np
import pytest

import gpu_util
from pointflow.render.base import RenderError
from pointflow.render.wgpu_tier import WgpuRenderer, merge_ranges, select_adapter

from .helpers import cfg


def test_merge_ranges():
    assert merge_ranges([(5, 10), (0, 3), (8, 12), (12, 14)], 100) == [(0, 3), (5, 14)]
    assert merge_ranges([(90, 10)], 100) == [(0, 10), (90, 100)]        # wraps around the ring end
    assert merge_ranges([(50, 150), (-5, 2)], 100) == [(0, 2), (50, 100)]
    assert merge_ranges([(3, 3)], 100) == []


def test_unknown_adapter_name_is_a_render_error(monkeypatch):
    monkeypatch.setenv("POINTFLOW_WGPU_ADAPTER", "no-such-adapter-xyz")
    adapter, why = select_adapter()
    assert adapter is None and "no-such-adapter-xyz" in why
    with pytest.raises(RenderError, match="no-such-adapter-xyz"):
        WgpuRenderer(cfg(), 100, [])


@pytest.mark.gpu
def test_info_and_capacity_caps(make_renderer):
    r = make_renderer(cfg(), 1000)
    info = r.info()
    assert info["tier"] == "wgpu" and info["render_capacity"] == 1000 and info["caps"] == []
    assert info["chunks"] == 1 and info["chunk_slots"] == 1000
    assert info["limits"]["max-storage-buffer-binding-size"] > 0 and isinstance(info["timestamps"], bool)
    # a ring beyond one storage binding is split into chunks that each fit one (nothing capped)
    r._limits = {"max-storage-buffer-binding-size": 16 * 600, "max-buffer-size": 1 << 30,
                 "max-compute-workgroups-per-dimension": 65535}
    table = r._chunk_plan(1000)
    assert sum(n for _, n in table) == 1000 and [a for a, _ in table] == sorted(a for a, _ in table)
    assert len(table) >= 2 and all(n * r._method_cls.slot_bytes <= 16 * 600 for _, n in table)
    r._limits["max-storage-buffer-binding-size"] = 1200  # not even 256 points: refused, with the numbers
    with pytest.raises(RenderError, match="1200 bytes"):
        r._chunk_plan(1000)


def test_require_adapter_fails_under_require_gpu(monkeypatch):
    monkeypatch.setattr(gpu_util, "_CACHE", {})
    monkeypatch.setenv("POINTFLOW_WGPU_ADAPTER", "no-such-adapter-xyz")
    monkeypatch.setenv("POINTFLOW_REQUIRE_GPU", "1")
    with pytest.raises(pytest.fail.Exception, match="POINTFLOW_REQUIRE_GPU=1"):
        gpu_util.require_adapter()
    monkeypatch.setattr(gpu_util, "_CACHE", {})
    monkeypatch.setenv("POINTFLOW_REQUIRE_GPU", "0")
    with pytest.raises(pytest.skip.Exception):
        gpu_util.require_adapter()


@pytest.mark.gpu
def test_malformed_frame_is_a_value_error_naming_the_field(make_renderer):
    from pointflow.render.camera import Camera
    from .helpers import frame
    r = make_renderer(cfg(), 10)
    cam = Camera(eye=[0.0, -10.0, 0.0], target=[0.0, 0.0, 0.0])
    f = frame(np.zeros((10, 3)))
    f.positions = np.zeros((10, 2), np.float32)
    with pytest.raises(ValueError, match="positions"):
        r.render(f, cam)
    f = frame(np.zeros((10, 3)))
    f.size = 11
    with pytest.raises(ValueError, match="size"):
        r.render(f, cam)
    r.render(frame(np.zeros((10, 3))), cam)       # the renderer is still usable
    assert r.finish().drawn == 10
