"""Eye-dome lighting in the wgpu tier's raster methods (quads: a post pass over a linear-depth
target; compute, both key layouts: in the resolve pass from the key buffer's depths) against
the cpu tier's float64 EDL image (pointflow.render.rules.edl_shade)."""
from __future__ import annotations

import dataclasses
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from pointflow.config import EdlConfig
from pointflow.render.cpu import CpuRenderer

_spec = importlib.util.spec_from_file_location(
    "render_tiers_scenes_edl", Path(__file__).resolve().parents[1] / "render_tiers" / "scenes.py")
S = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(S)  # type: ignore[union-attr]

EDL_ON = EdlConfig(enabled=True)
SCENES = [*S.SCENES, "walls"]


def _scene(name):
    return S.walls() if name == "walls" else S.SCENES[name]()


def _cfg(kw, edl=None):
    cfg = S.render_cfg(size=[320, 240], **kw)
    return dataclasses.replace(cfg, edl=edl) if edl is not None else cfg


def _img(r, frame, cam):
    r.render(frame, cam)
    return r.read_image()


@pytest.mark.parametrize("scene", SCENES)
def test_wgpu_edl_matches_the_cpu_reference(make_renderer, raster, scene):
    """<= 0.1% of pixels differ from the cpu EDL image by more than one 8-bit step (the GPU
    shades in float32), for every raster method (quads applies the cpu footprint rule per
    pixel centre and orders by linear depth, so no pixel is exempt); <= 1% differ at all."""
    frame, cam, kw = _scene(scene)
    ch = list(frame.channels)
    ref = _img(CpuRenderer(_cfg(kw, EDL_ON), frame.capacity, ch), frame, cam)
    plain_ref = _img(CpuRenderer(_cfg(kw), frame.capacity, ch), frame, cam)
    img = _img(make_renderer(_cfg(kw, EDL_ON), frame.capacity, ch), frame, cam)
    assert (ref != plain_ref).any(-1).mean() > 0.01, "EDL must change the scene for the comparison to mean anything"
    beyond = np.abs(img.astype(np.int16) - ref).max(axis=-1) > 1
    assert beyond.mean() <= 0.001, f"{raster} EDL differs from cpu by > 1 step in {beyond.mean():.3%} of pixels"
    d = float((img != ref).any(-1).mean())
    assert d <= 0.01, f"{raster} EDL differs from cpu in {d:.2%} of pixels on {scene}"


def test_edl_works_with_every_colour_mode_and_off_is_unchanged(make_renderer, raster):
    """Every colour source and the auto range (reduced on the GPU in the same frame) with EDL
    on; EDL off leaves the image as it was."""
    w = S.terrain(8_000, seed=3)
    rgb = (np.abs(w) * 7 % 255).astype(np.uint8)
    frame = S.make_frame(w, rgb=rgb, t_ms=np.linspace(0, 500, len(w)), now_ms=500.0)
    cam = S.terrain_camera()
    ch = list(frame.channels)
    for colour in ({"color_by": None}, {"color_by": "rgb"}, {"color_by": "intensity", "color_range": "auto"},
                   {"color_by": "z"}, {"color_by": "ingest_time"}):
        kw = dict(point_size=2, **colour)
        plain = _img(make_renderer(_cfg(kw), frame.capacity, ch), frame, cam)
        off = _img(make_renderer(_cfg(kw, EdlConfig(enabled=False, strength=3.0)), frame.capacity, ch), frame, cam)
        on = _img(make_renderer(_cfg(kw, EDL_ON), frame.capacity, ch), frame, cam)
        ref = _img(CpuRenderer(_cfg(kw, EDL_ON), frame.capacity, ch), frame, cam)
        assert (off == plain).all(), colour
        assert (on[..., :3] <= plain[..., :3]).all() and (on != plain).any(-1).mean() > 0.01, colour
        assert (np.abs(on.astype(np.int16) - ref).max(-1) > 1).mean() <= 0.01, colour
