"""Where methods fail (issue 7): each case asserts a specific outcome, in every tier."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import diff_fraction, draw, ring_to_frames
from scenes import grid_plane, make_frame, render_cfg, sphere_shell

from pointflow.config import ConfigError, load_config
from pointflow.render.camera import Camera
from pointflow.render.cpu import CpuRenderer
from pointflow.render.rules import rgba_u8

GEO = np.array([6.4e5, 4.9e6, 0.0])
CAM = Camera(eye=[0, 0, 10], target=[0, 0, 0], up=[0, 1, 0], fov_deg=60, near=1, far=100)


def lit(img):
    return (img != img[0, 0]).any(axis=-1) if False else (img[..., :3] != 0).any(axis=-1)


def black(**kw):
    return render_cfg(background=[0, 0, 0], **kw)


# ------------------------------------------------------------------ large coordinates
def test_georeferenced_offsets_render_like_local_and_naive_float32_does_not(make):
    pts = grid_plane(step=0.05, half=2.0)
    cam = Camera(eye=[0.3, -3.0, 2.5], target=[0, 0, 0], near=0.5, far=20)
    cfg = render_cfg(size=[320, 240], point_size=1, color_by=None)
    inten = np.linspace(0, 1, len(pts), dtype=np.float32)
    local, _ = draw(make(cfg, len(pts)), make_frame(pts, intensity=inten), cam)
    far, _ = draw(make(cfg, len(pts)), make_frame(pts + GEO, origin=GEO, intensity=inten), cam.translated(GEO))
    naive, _ = draw(make(cfg, len(pts)), make_frame(pts + GEO, naive_f32=True, intensity=inten), cam.translated(GEO))
    assert lit(local).mean() > 0.2
    assert diff_fraction(local, far) <= 0.001
    assert diff_fraction(local, naive) > 0.05  # float32 steps of 0.5 m at y = 4.9e6 collapse the grid


# ------------------------------------------------------------------ frustum edges
def test_points_exactly_on_near_and_far_planes_are_kept(make):
    cam = Camera(eye=[0, 0, 0], target=[0, 0, -1], up=[0, 1, 0], fov_deg=60, near=1.0, far=2.0)
    pts = [[0.2, 0.0, -1.0], [-0.4, 0.0, -2.0], [0.0, 0.3, -1.5], [0.0, 0.0, -2.0001], [0.0, 0.0, -0.9999]]
    inten = np.array([0.0, 0.5, 1.0, 0.25, 0.75], np.float32)
    cfg = black(size=[64, 64], point_size=2, color_range=[0, 1])
    r = make(cfg, 5)
    planes = cam.frustum_planes(64, 64)
    d = np.asarray(pts) @ planes[:, :3].T + planes[:, 3]
    assert (d[:2].min(axis=1) == 0).all()  # exactly on a plane, in float64
    img, st = draw(r, make_frame(pts, intensity=inten), cam)
    from pointflow.render import colormap
    lut = colormap.lut("turbo")
    colours = {tuple(c) for c in img.reshape(-1, 4)} - {(0, 0, 0, 255)}
    assert colours == {tuple(lut[0]), tuple(lut[128]), tuple(lut[255])}  # on-plane kept, outside culled
    if st.drawn is not None:
        assert st.drawn == 3


def test_camera_inside_the_cloud_with_tiny_near_plane(make):
    shell = sphere_shell(20_000, r=10.0)
    rng = np.random.default_rng(5)
    close = rng.normal(scale=0.3, size=(500, 3))
    pts = np.vstack([shell, close, [[0.0, 2e-4, 0.0]]])  # one point 2e-4 in front of the eye
    cam = Camera(eye=[0, 0, 0], target=[0, 1, 0], up=[0, 0, 1], near=1e-4, far=50)
    cfg = render_cfg(size=[200, 150], point_size=3)
    f = make_frame(pts, intensity=np.linspace(0, 1, len(pts), dtype=np.float32))
    ref, ref_st = draw(CpuRenderer(cfg, len(pts), ["intensity"]), f, cam)
    img, st = draw(make(cfg, len(pts)), f, cam)
    assert (ref != rgba_u8(cfg.background)).any(axis=-1).mean() > 0.3
    assert ref_st.extra["removed_frustum"] > 0  # the shell behind the camera is culled, not drawn
    assert diff_fraction(img, ref) <= 0.01


# ------------------------------------------------------------------ bad values
def test_nan_and_inf_positions_are_not_drawn_and_are_counted(make, tier):
    rng = np.random.default_rng(1)
    good = np.column_stack([rng.uniform(-4, 4, 1000), rng.uniform(-4, 4, 1000), np.zeros(1000)])
    bad = good[:60].copy()
    bad[0::3, 0] = np.nan
    bad[1::3, 1] = np.inf
    bad[2::3, 2] = -np.inf
    mixed = np.empty((1060, 3))
    mixed[0::2][:60], mixed[1::2][:60] = bad, good[:60]  # interleaved
    mixed[120:] = good[60:]
    inten = np.ones(1060, np.float32)
    cfg = render_cfg(size=[128, 128], point_size=2)
    clean, _ = draw(make(cfg, 1060), make_frame(good, intensity=inten[:1000]), CAM)
    img, st = draw(make(cfg, 1060), make_frame(mixed, intensity=inten), CAM)
    assert diff_fraction(img, clean) <= 0.001
    assert st.extra["removed_nonfinite"] == 60


def test_all_equal_importance_samples_uniformly_and_evicts_fifo(make):
    from pointflow.ring import PointRing

    ring = PointRing(100, channels=["intensity"], eviction="importance", importance_field="intensity")
    try:
        xs = np.linspace(-4, 4, 150)
        ring.push(np.column_stack([xs, np.zeros(150), np.zeros(150)]), intensity=np.full(150, 0.5, np.float32))
        snap = ring.snapshot()
        assert np.allclose(snap.positions[:, 0], xs[50:])  # FIFO: the 50 oldest went
        cfg = render_cfg(size=[256, 32], point_size=1, importance_sampling=True, color_by=None)
        off = render_cfg(size=[256, 32], point_size=1, importance_sampling=False, color_by=None)
        with ring_to_frames(ring) as next_frame:
            f = next_frame()
            img, st = draw(make(cfg, 100), f, CAM)
            ref, _ = draw(make(off, 100), f, CAM)
        assert (img == ref).all()  # degenerate range: every point kept
        if st.drawn is not None:
            assert st.drawn == 100
    finally:
        ring.close()
        ring.unlink()


def test_zero_importance_everywhere_draws_everything(make):
    """Documented outcome: a degenerate importance range (all zero) carries no information,
    so sampling keeps every point (p = 1) instead of blanking the screen."""
    rng = np.random.default_rng(2)
    pts = np.column_stack([rng.uniform(-4, 4, 800), rng.uniform(-4, 4, 800), np.zeros(800)])
    f = make_frame(pts, importance=np.zeros(800, np.float32))
    img, st = draw(make(render_cfg(size=[96, 96], importance_sampling=True), 800), f, CAM)
    ref, _ = draw(make(render_cfg(size=[96, 96]), 800), f, CAM)
    assert (img == ref).all() and (img != img[0, 0]).any(axis=-1).mean() > 0.2
    if st.drawn is not None:
        assert st.drawn == 800


# ------------------------------------------------------------------ ring sizes
def test_empty_ring_draws_background(make):
    cfg = render_cfg(size=[48, 32])
    f = make_frame(np.zeros((0, 3)), capacity=16)
    img, st = draw(make(cfg, 16), f, CAM)
    assert (img == rgba_u8(cfg.background)).all()
    assert st.drawn in (0, None)


def test_ring_of_one_point_through_the_slab_path(make):
    from pointflow.ring import PointRing

    ring = PointRing(1, channels=["intensity"])
    try:
        ring.push(np.array([[0.0, 0.0, 0.0]]), intensity=np.array([1.0], np.float32))
        ring.push(np.array([[1.0, 1.0, 0.0]]), intensity=np.array([1.0], np.float32))  # replaces it
        with ring_to_frames(ring) as next_frame:
            f = next_frame()
            cfg = black(size=[64, 64], point_size=2, color_by=None)
            img, _ = draw(make(cfg, 1), f, CAM)
        ys, xs = np.nonzero(lit(img))
        assert len(xs) == 4
        px = (CAM.view_proj(64, 64) @ [1, 1, 0, 1])
        cx, cy = (px[0] / px[3] * 0.5 + 0.5) * 64, (0.5 - px[1] / px[3] * 0.5) * 64
        assert abs(xs.mean() + 0.5 - cx) < 1 and abs(ys.mean() + 0.5 - cy) < 1
    finally:
        ring.close()
        ring.unlink()


def test_chunk_larger_than_the_ring_keeps_the_newest(make):
    from pointflow.ring import PointRing

    ring = PointRing(64, channels=["intensity"])
    try:
        xs = np.concatenate([np.linspace(-1000, -900, 936), np.linspace(-80, 80, 64)])  # only the newest in view
        pts = np.column_stack([xs, np.zeros(1000), np.zeros(1000)])
        ring.push(pts, intensity=np.linspace(0, 1, 1000, dtype=np.float32))
        cfg = render_cfg(size=[512, 32], point_size=1, color_range=[0, 1])
        with ring_to_frames(ring) as next_frame:
            img, _ = draw(make(cfg, 64), next_frame(), CAM)
        want, _ = draw(CpuRenderer(cfg, 64, ["intensity"]),
                       make_frame(pts[-64:], intensity=np.linspace(0, 1, 1000, dtype=np.float32)[-64:]), CAM)
        assert diff_fraction(img, want) <= 0.001
        assert (img != img[0, 0]).any(axis=-1).sum() >= 60
    finally:
        ring.close()
        ring.unlink()


# ------------------------------------------------------------------ sizes and viewports
@pytest.mark.parametrize("size,count", [(1, 1), (128, 128 * 128)])
def test_point_sizes_1_and_128(make, size, count):
    cfg = black(size=[256, 256], point_size=size, color_by=None)
    img, _ = draw(make(cfg, 1), make_frame([[0, 0, 0]]), CAM)
    assert lit(img).sum() == count


def test_one_by_one_viewport(make):
    cfg = black(size=[1, 1], point_size=1, color_by=None)
    img, _ = draw(make(cfg, 1), make_frame([[0, 0, 0]]), CAM)
    assert img.shape == (1, 1, 4) and lit(img).all()
    img, _ = draw(make(cfg, 1), make_frame([[50, 0, 0]]), CAM)  # outside: background
    assert not lit(img).any()


def test_wide_4096x64_viewport(make):
    cfg = render_cfg(size=[4096, 64], point_size=2)
    xs = np.linspace(-60, 60, 3000)
    pts = np.column_stack([xs, np.sin(xs) * 0.15, np.zeros_like(xs)])
    f = make_frame(pts)
    ref, _ = draw(CpuRenderer(cfg, len(pts), ["intensity"]), f, CAM)
    img, _ = draw(make(cfg, len(pts)), f, CAM)
    assert img.shape == (64, 4096, 4)
    assert (ref != ref[0, 0]).any(axis=-1).sum() > 1000
    assert diff_fraction(img, ref) <= 0.01


@pytest.mark.parametrize("size", [[0, 64], [64, 0]])
def test_zero_size_viewport_rejected_at_config_load(size):
    with pytest.raises(ConfigError) as e:
        load_config({"source": {"transport": "synthetic"}, "render": {"size": size}})
    assert e.value.path == "render.size"
