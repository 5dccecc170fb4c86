"""The legend a view frame carries (render/view/legend.py) names the range the tiers colour with
(render/rules.py ``color_values``), in world units, and the page's LUT is the render stage's."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from pointflow.render.base import FrameInput
from pointflow.render.colormap import NAMES, lut
from pointflow.render.view.legend import camera_dict, legend_dict, lut_hex
from pointflow.render.rules import color_values
from pointflow.render.camera import Camera


def _frame(size: int, cap: int = 5000) -> FrameInput:
    rng = np.random.default_rng(3)
    pos = (rng.random((cap, 3)) * 50 - 10).astype(np.float32)
    pos[5, 1], pos[7, 2] = np.nan, np.inf  # positions a tier skips
    t = rng.random(cap) * 1e4
    t[9] = np.nan
    return FrameInput(positions=pos, importance=np.ones(cap, np.float32), t_ingest_ms=t,
                      channels={"intensity": rng.random(cap).astype(np.float32) * 7},
                      head=1234, size=size, capacity=cap, origin=np.array([6.4e5, 0.0, 300.0]), now_ms=0.0,
                      channel_ranges={})


@pytest.mark.parametrize("size", [5000, 3100])
@pytest.mark.parametrize("cb", ["z", "ingest_time", "intensity"])
def test_the_auto_range_is_the_tiers(cb, size):
    f = _frame(size)
    lg = legend_dict(f, SimpleNamespace(color_by=cb, color_range="auto", colormap="viridis"))
    _, (lo, hi) = color_values(f, SimpleNamespace(color_by=cb, color_range="auto"), np.empty(0, np.int64))
    shift = 300.0 if cb == "z" else 0.0
    assert lg == {"color_by": cb, "colormap": "viridis", "auto": True, "range": [lo + shift, hi + shift],
                  "unit": "m" if cb == "z" else ""}
    if cb == "z":  # a map in feet (its CRS): the legend says so
        ft = legend_dict(f, SimpleNamespace(color_by=cb, color_range="auto", colormap="viridis"), {"xy": "ft", "z": "ft"})
        assert ft["unit"] == "ft" and ft["range"] == lg["range"]


def test_fixed_range_handoff_range_and_no_legend():
    f = _frame(5000)
    fixed = legend_dict(f, SimpleNamespace(color_by="z", color_range=[290.0, 310.0], colormap="turbo"))
    assert fixed["range"] == [290.0, 310.0] and not fixed["auto"]  # world z, as the style says it
    f.channel_ranges["intensity"] = (1.0, 2.0)
    assert legend_dict(f, SimpleNamespace(color_by="intensity", color_range="auto",
                                          colormap="turbo"))["range"] == [1.0, 2.0]
    for cb in (None, "none", "rgb", "not_a_channel"):
        assert legend_dict(f, SimpleNamespace(color_by=cb, color_range="auto", colormap="turbo")) is None


def test_lut_hex_and_camera_dict():
    for name in NAMES:
        h = lut_hex(name)
        assert np.array_equal(np.frombuffer(bytes.fromhex(h), np.uint8).reshape(256, 3), lut(name)[:, :3])
    c = camera_dict(Camera(eye=[1, 2, 3], target=[0, 0, 0], fov_deg=45.0, near=0.5, far=90.0))
    assert c == {"eye": [1.0, 2.0, 3.0], "target": [0.0, 0.0, 0.0], "up": [0.0, 0.0, 1.0], "fov_deg": 45.0,
                 "near": 0.5, "far": 90.0}
