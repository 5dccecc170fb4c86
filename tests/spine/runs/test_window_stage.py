"""The render stage opens a window when ``render.window`` is set and a display exists
(Xvfb here), keeps writing PNGs, and falls back to headless without a display."""
from __future__ import annotations

import os

from pointflow import Pipeline

from ..helpers import small_config


def test_render_stage_with_a_window(tmp_path):
    from gpu_util import require_adapter, xvfb_display

    require_adapter()
    with xvfb_display():
        cfg = small_config(render={"backend": "wgpu", "size": [160, 120], "window": True,
                                   "output": {"every_n_frames": 2}})
        with Pipeline.from_dict(cfg, out_dir=str(tmp_path)) as pipe:
            pipe.wait(60, until=lambda: pipe.stats()["frames"] >= 4)
            render = pipe.stats()["stages"]["render"]
    assert render.get("window") is True, "no window was opened"
    assert render["frames"] >= 4
    assert list(tmp_path.glob("frame_*.png")), "PNG output stops when a window is open"


def test_window_without_display_renders_headless(tmp_path, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    cfg = small_config(render={"backend": "cpu", "size": [160, 120], "window": True})
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path)) as pipe:
        pipe.wait(60, until=lambda: pipe.stats()["frames"] >= 2)
        render = pipe.stats()["stages"]["render"]
    assert render["frames"] >= 2 and "window" not in render
    assert not os.environ.get("DISPLAY")
