"""The shared rasterisation, depth, colour and selection rules, checked in every tier."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import draw
from scenes import make_frame, render_cfg

from pointflow.render import colormap
from pointflow.render.camera import Camera
from pointflow.render.rules import rgba_u8

# Camera on +z looking at the origin: the origin projects to the viewport centre exactly.
CAM = Camera(eye=[0, 0, 10], target=[0, 0, 0], up=[0, 1, 0], fov_deg=60, near=1, far=100)


def lit(img, bg):
    return (img != bg).any(axis=-1)


def footprint(make, size, shape, W=16, H=16, point=(0.0, 0.0, 0.0)):
    cfg = render_cfg(size=[W, H], point_size=size, point_shape=shape, color_by=None, background=[0, 0, 0])
    r = make(cfg, 1)
    img, st = draw(r, make_frame([point]), CAM)
    assert st.drawn in (1, None)  # None: the GPU tier does not read the count back
    return set(zip(*np.nonzero(lit(img, rgba_u8(cfg.background)))))


def block(r0, r1, c0, c1):
    return {(r, c) for r in range(r0, r1) for c in range(c0, c1)}


def test_square_footprints_follow_half_open_rule(make):
    # centre (8, 8): size 2 covers centres in [7, 9) → pixels 7, 8; size 3 → [6.5, 9.5) → 6..8
    assert footprint(make, 2, "square") == block(7, 9, 7, 9)
    assert footprint(make, 3, "square") == block(6, 9, 6, 9)
    assert footprint(make, 1, "square") == {(7, 7)}  # [7.5, 8.5) holds centre 7.5 only


def test_round_footprints_follow_inclusive_radius(make):
    assert footprint(make, 3, "round") == block(7, 9, 7, 9)  # (6.5, 7.5) is 1.58 > 1.5 away
    four = footprint(make, 4, "round")  # radius 2: 4x4 minus the corners (2.12 away)
    assert four == block(6, 10, 6, 10) - {(6, 6), (6, 9), (9, 6), (9, 9)}


def test_nearer_point_wins_regardless_of_order(make):
    cfg = render_cfg(size=[16, 16], point_size=4, color_range=[0, 1])
    for near_first in (True, False):
        pts = [[0, 0, 1.0], [0, 0, 0.0]] if near_first else [[0, 0, 0.0], [0, 0, 1.0]]
        inten = [1.0, 0.0] if near_first else [0.0, 1.0]  # the near point has intensity 1
        img, _ = draw(make(cfg, 2), make_frame(pts, intensity=np.array(inten, np.float32)), CAM)
        assert tuple(img[8, 8]) == tuple(colormap.lut("turbo")[255])


def test_equal_depth_ties_go_to_lower_logical_index(make, tier, request):
    cfg = render_cfg(size=[16, 16], point_size=4, color_range=[0, 1])
    # slots wrap: logical 0 sits in slot 2, logical 1 in slot 0
    f = make_frame([[0, 0, 0], [0, 0, 0]], capacity=3, head=2, intensity=np.array([0.0, 1.0], np.float32))
    img, _ = draw(make(cfg, 3), f, CAM)
    assert tuple(img[8, 8]) == tuple(colormap.lut("turbo")[0])


def test_colormap_nan_single_colour_and_rgb(make):
    cfg = render_cfg(size=[32, 16], point_size=2, color=[1.0, 0.0, 1.0], color_range=[0, 10])
    pts = [[-2, 0, 0], [0, 0, 0], [2, 0, 0]]
    f = make_frame(pts, intensity=np.array([0.0, 10.0, np.nan], np.float32))
    img, _ = draw(make(cfg, 3), f, CAM)
    cols = {tuple(img[8, x]) for x in range(32)} - {tuple(rgba_u8(cfg.background))}
    lut = colormap.lut("turbo")
    assert cols == {tuple(lut[0]), tuple(lut[255]), (255, 0, 255, 255)}
    cfg2 = render_cfg(size=[32, 16], point_size=2, color_by="rgb")
    f2 = make_frame(pts, rgb=np.array([[10, 20, 30], [40, 50, 60], [70, 80, 90]], np.uint8))
    img2, _ = draw(make(cfg2, 3, ("rgb",)), f2, CAM)
    cols2 = {tuple(img2[8, x]) for x in range(32)} - {tuple(rgba_u8(cfg2.background))}
    assert cols2 == {(10, 20, 30, 255), (40, 50, 60, 255), (70, 80, 90, 255)}


def test_time_window_is_inclusive_and_off_at_zero(make):
    pts = [[-2, 0, 0], [0, 0, 0], [2, 0, 0]]
    f = make_frame(pts, t_ms=np.array([0.0, 50.0, 80.0]), now_ms=100.0)
    for window, drawn in ((50.0, 2), (49.0, 1), (0.0, 3)):
        cfg = render_cfg(size=[32, 16], time_window_ms=window)
        r = make(cfg, 3)
        img, st = draw(r, f, CAM)
        assert st.drawn in (drawn, None)
        assert len({x for x in range(32) if (img[8, x] != img[0, 0]).any()}) // 2 == drawn  # 2 px each


def test_lod_stride_keeps_every_kth_logical_point(make):
    pts = np.column_stack([np.linspace(-3, 3, 12), np.zeros(12), np.zeros(12)])
    f = make_frame(pts, capacity=16, head=9)
    cfg = render_cfg(size=[64, 16], lod_stride=4, point_size=1, color_range=[0, 1])
    r = make(cfg, 16)
    img, st = draw(r, f, CAM)
    if st.drawn is not None:
        assert st.drawn == 3
    from pointflow.render.cpu import CpuRenderer
    ref = CpuRenderer(cfg, 16, ["intensity"])
    ref.render(f, CAM)
    ys, xs = np.nonzero(lit(ref.read_image(), rgba_u8(cfg.background)))
    assert len(xs) == 3  # logical 0, 4, 8
    assert (img == ref.read_image()).all()


def test_budget_caps_the_drawn_count(make):
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(-4, 4, 2000), rng.uniform(-4, 4, 2000), np.zeros(2000)])
    f = make_frame(pts, budget=300, seed=5)
    r = make(render_cfg(size=[64, 64], point_size=1), 2000)
    img, st = draw(r, f, CAM)
    n_lit = int(lit(img, rgba_u8(r.cfg.background)).sum())
    assert 0 < n_lit <= 300
    if st.drawn is not None:
        assert 200 <= st.drawn <= 300  # hash thinning aims at b - 3 sqrt(b) = 248, capped at b


def test_pick_returns_the_front_point_and_scales_by_pixel_ratio(make, tier):
    cfg = render_cfg(size=[32, 32], point_size=4, pick_radius=2)
    f = make_frame([[0, 0, 0.0], [0, 0, 2.0], [3, 3, 0]], capacity=4, head=1)  # slots 1, 2, 3
    r = make(cfg, 4)
    r.render(f, CAM)
    assert r.pick(16, 16) == 2                  # the nearer of two stacked points
    assert r.pick(8, 8, pixel_ratio=2.0) == 2
    assert r.pick(1, 30) is None


@pytest.mark.parametrize("offset, picked", [((6, 6), False), ((5, 5), True), ((8, 0), True), ((0, -8), True),
                                            ((6, -6), False), ((-7, 5), False)])
def test_pick_radius_is_a_circle_in_every_tier(make, offset, picked):
    """A pixel counts when its centre is within pick_radius of the cursor: (6, 6) is 8.49 px
    away, outside radius 8, though inside the 17 x 17 square around the cursor."""
    cfg = render_cfg(size=[32, 32], point_size=1, pick_radius=8, color_by=None, background=[0, 0, 0])
    r = make(cfg, 4)
    r.render(make_frame([[0, 0, 0.0]], capacity=4, head=2), CAM)
    ys, xs = np.nonzero(lit(r.read_image(), rgba_u8(cfg.background)))
    assert len(xs) == 1
    cx, cy = xs[0] + 0.5 + offset[0], ys[0] + 0.5 + offset[1]  # the cursor, offset from the pixel centre
    assert r.pick(cx, cy) == (2 if picked else None)
    # at pixel_ratio 2 the radius is 16 framebuffer px: the same offsets, doubled, give the same answers
    cx2, cy2 = xs[0] + 0.5 + 2 * offset[0], ys[0] + 0.5 + 2 * offset[1]
    assert r.pick(cx2 / 2, cy2 / 2, pixel_ratio=2.0) == (2 if picked else None)
