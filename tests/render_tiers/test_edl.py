"""Eye-dome lighting (render.edl): the float64 rule in rules.py, the cpu reference, and every
tier that implements it agreeing with the cpu image (docs/render-tiers.md#eye-dome-lighting-renderedl)."""
from __future__ import annotations

import dataclasses
import hashlib

import numpy as np
import pytest

from conftest import TIERS, diff_fraction, draw
from scenes import SCENES, WALL_BACK_RGB, WALL_FRONT_RGB, render_cfg, walls

from pointflow.config import ConfigError, EdlConfig, load_config
from pointflow.render.cpu import CpuRenderer
from pointflow.render.rules import apply_shade, edl_offsets, edl_shade

#: Tiers with EDL: every tier (cpu, gl, both wgpu raster methods).
EDL_TIERS = TIERS
EDL_ON = EdlConfig(enabled=True)


def _cfg(kw, edl=None, **more):
    cfg = render_cfg(size=[320, 240], **kw, **more)
    return dataclasses.replace(cfg, edl=edl) if edl is not None else cfg


# --------------------------------------------------------------------------- the rule
def test_offsets_are_rounded_once_with_python_round():
    assert edl_offsets(1.4).tolist() == [[1, 0], [1, 1], [0, 1], [-1, 1], [-1, 0], [-1, -1], [0, -1], [1, -1]]
    # r cos(pi/4) = 1.77 -> 2; r = 2.5 -> 2 (half to even)
    assert edl_offsets(2.5).tolist() == [[2, 0], [2, 2], [0, 2], [-2, 2], [-2, 0], [-2, -2], [0, -2], [2, -2]]
    assert edl_offsets(3).tolist()[1] == [2, 2] and edl_offsets(3).dtype == np.int32


def test_shade_formula_by_hand():
    """Response = mean over 8 neighbours of max(0, d(p) - d(q)); background and outside
    neighbours contribute 0; background pixels keep shade 1."""
    d = np.array([[3.0, 1.0, 0.0],
                  [2.0, 2.0, 0.0],
                  [9.0, 9.0, 9.0]])
    cov = np.array([[True, True, False],
                    [True, True, False],
                    [False, False, False]])
    s = edl_shade(d, cov, edl_offsets(1.4), strength=0.01)
    # (0,0) = 3: neighbours right (1) and below (2), below-right (2): (2 + 1 + 1) / 8
    assert s[0, 0] == pytest.approx(np.exp(-3.0 * 4 / 8))
    # (1,1) = 2: neighbours (0,0)=3, (0,1)=1, (1,0)=2 -> only 2 - 1 = 1 counts
    assert s[1, 1] == pytest.approx(np.exp(-3.0 * 1 / 8))
    assert s[0, 1] == 1.0  # the nearest pixel is never darkened
    assert (s[~cov] == 1.0).all()  # no halo on the background
    img = np.full((3, 3, 4), 200, np.uint8)
    out = apply_shade(img, s)
    assert (out[~cov] == 200).all() and (out[..., 3] == 200).all()
    assert out[0, 0, 0] == np.floor(200 * np.exp(-1.5) + 0.5)


def test_edl_config_is_validated():
    base = {"sources": [{"transport": "synthetic"}]}
    cfg = load_config({**base, "render": {"edl": {"enabled": True, "strength": 2, "radius_px": 2.5}}})
    assert cfg.render.edl == EdlConfig(enabled=True, strength=2.0, radius_px=2.5)
    assert load_config(base).render.edl.enabled is False
    for bad, path in (({"strength": -1}, "render.edl.strength"), ({"radius_px": 0.5}, "render.edl.radius_px"),
                      ({"enabled": "yes"}, "render.edl.enabled"), ({"radius": 2}, "render.edl")):
        with pytest.raises(ConfigError) as e:
            load_config({**base, "render": {"edl": bad}})
        assert str(e.value).startswith(path), str(e.value)


# --------------------------------------------------------------------------- EDL off
#: sha256 (first 16 hex) of the cpu image of each agreement scene at 320x240, rendered by
#: the code before EDL existed (commit b2b1037): EDL off must give exactly these images.
BEFORE_EDL = {"terrain": "3a74e8eb93f9ede8", "sphere": "fdf9752b15f27cec",
              "georeferenced": "afd65ae0667f007b", "world_rgb_filters": "7f2626e3a1e444ec"}


@pytest.mark.parametrize("scene", list(SCENES))
def test_edl_off_gives_the_cpu_image_from_before_edl(scene):
    frame, cam, kw = SCENES[scene]()
    img, _ = draw(CpuRenderer(_cfg(kw), frame.capacity, list(frame.channels)), frame, cam)
    assert hashlib.sha256(img.tobytes()).hexdigest()[:16] == BEFORE_EDL[scene]


@pytest.mark.parametrize("tier", EDL_TIERS)
def test_edl_off_ignores_the_edl_settings_and_on_changes_the_image(make, tier):
    frame, cam, kw = SCENES["terrain"]()
    ch = list(frame.channels)
    plain, _ = draw(make(_cfg(kw), frame.capacity, ch), frame, cam)
    off, _ = draw(make(_cfg(kw, EdlConfig(enabled=False, strength=5.0, radius_px=3.0)), frame.capacity, ch),
                  frame, cam)
    on, _ = draw(make(_cfg(kw, EDL_ON), frame.capacity, ch), frame, cam)
    zero, _ = draw(make(_cfg(kw, EdlConfig(enabled=True, strength=0.0)), frame.capacity, ch), frame, cam)
    assert (off == plain).all()
    assert (zero == plain).all(), "strength 0 must leave every colour as it was (shade exactly 1)"
    assert diff_fraction(on, plain) > 0.05
    assert (on[..., :3] <= plain[..., :3]).all(), "EDL only darkens"


# --------------------------------------------------------------------------- EDL on
@pytest.mark.parametrize("tier", EDL_TIERS)
def test_wall_in_front_of_wall_darkens_the_far_wall_at_the_edge(make, tier):
    """Fails if EDL does nothing (edge not darker), inverts depth (the near wall darkened)
    or leaks (a halo on the background, or darkening far from any edge)."""
    frame, cam, kw = walls()
    ch = list(frame.channels)
    off, _ = draw(make(_cfg(kw), frame.capacity, ch), frame, cam)
    on, _ = draw(make(_cfg(kw, EDL_ON), frame.capacity, ch), frame, cam)
    front = (off[..., :3] == WALL_FRONT_RGB).all(-1)
    back = (off[..., :3] == WALL_BACK_RGB).all(-1)
    assert front.mean() > 0.05 and back.mean() > 0.3, "the scene must show both walls"
    H, W = front.shape
    # back-wall pixels with a front-wall pixel among their EDL neighbours / within 3 px
    touches = np.zeros_like(front)
    near = np.zeros_like(front)
    pad = np.pad(front, 3)
    for dx, dy in edl_offsets(EDL_ON.radius_px):
        touches |= pad[3 + dy:3 + dy + H, 3 + dx:3 + dx + W]
    for dy in range(-3, 4):
        for dx in range(-3, 4):
            near |= pad[3 + dy:3 + dy + H, 3 + dx:3 + dx + W]
    edge, far = back & touches, back & ~near
    assert edge.sum() > 50
    # each edge pixel sees at least one neighbour twice as near: shade <= exp(-300/8 * 1)
    assert (on[edge][:, 1] < off[edge][:, 1] // 2).all(), "the far wall must be darker along the near wall's outline"
    assert (on[front] == off[front]).all(), "the near wall must not be darkened (depth inverted?)"
    assert (on[far] == off[far]).all(), "a flat wall away from any edge must stay as it was"
    assert (on[~(front | back)] == off[~(front | back)]).all(), "no halo on the background"


@pytest.mark.parametrize("tier", EDL_TIERS)
def test_picking_is_unaffected_by_edl(make, tier):
    frame, cam, kw = SCENES["terrain"]()
    ch = list(frame.channels)
    plain, on = make(_cfg(kw), frame.capacity, ch), make(_cfg(kw, EDL_ON), frame.capacity, ch)
    plain.render(frame, cam)
    on.render(frame, cam)
    picks = [(x, y) for x in range(5, 320, 37) for y in range(5, 240, 29)]
    got = [plain.pick(x, y) for x, y in picks]
    assert sum(g is not None for g in got) > 10
    assert [on.pick(x, y) for x, y in picks] == got


@pytest.mark.parametrize("scene", [*SCENES, "walls"])
# wgpu-quads: tests/render_wgpu/test_edl_wgpu.py (its rasteriser's footprint edges differ
# from the cpu rule in ~0.1% of pixels before EDL; compared there outside those)
@pytest.mark.parametrize("tier", [t for t in EDL_TIERS if t not in ("cpu", "wgpu-quads")])
def test_edl_matches_the_cpu_reference(make, tier, scene):
    """Same EDL image as the cpu tier's float64 one: at most 0.1% of pixels differ by more
    than one 8-bit step (the GPU computes the shade in float32, so a colour may round the
    other way), and at most 1% differ at all (the bound of test_agreement.py)."""
    frame, cam, kw = walls() if scene == "walls" else SCENES[scene]()
    cfg = _cfg(kw, EDL_ON)
    ch = list(frame.channels)
    ref, _ = draw(CpuRenderer(cfg, frame.capacity, ch), frame, cam)
    img, _ = draw(make(cfg, frame.capacity, ch), frame, cam)
    plain, _ = draw(CpuRenderer(_cfg(kw), frame.capacity, ch), frame, cam)
    assert diff_fraction(ref, plain) > 0.01, "EDL must change the scene for the comparison to mean anything"
    beyond_one = float((np.abs(img.astype(np.int16) - ref).max(axis=-1) > 1).mean())
    assert beyond_one <= 0.001, f"{tier} EDL differs from cpu by > 1 step in {beyond_one:.3%} of pixels on {scene}"
    d = diff_fraction(img, ref)
    assert d <= 0.01, f"{tier} EDL differs from cpu in {d:.2%} of pixels on {scene}"
