"""cpu tier specifics: determinism, the shared hash, sampling statistics, picking."""
from __future__ import annotations

import numpy as np

from scenes import make_frame, render_cfg, terrain, terrain_camera

from pointflow.render.camera import Camera
from pointflow.render.cpu import CpuRenderer
from pointflow.render.rules import pcg_hash, seed_hash, select_points, uniform01

CAM = Camera(eye=[0, 0, 10], target=[0, 0, 0], up=[0, 1, 0], fov_deg=60, near=1, far=100)


def test_pcg_hash_vectors_and_wgpu_reference():
    assert int(pcg_hash(0, 0)[0]) == 817759070
    assert int(pcg_hash(1, 7)[0]) == 2809854175
    try:
        from pointflow.render.wgpu_tier import reference as R
    except ImportError:
        return
    s = np.arange(50_000)
    for seed in (0, 1, 2**31 + 5):
        assert (R.uniform01(s, R.seed_hash(seed)) == uniform01(s, seed_hash(seed))).all()


def test_bit_for_bit_deterministic():
    w = terrain(30_000)
    f = make_frame(w, capacity=40_000, head=25_000, intensity=(w[:, 2] + 3) / 14)
    cfg = render_cfg(size=[200, 150], point_size=3, point_shape="round")
    a = CpuRenderer(cfg, f.capacity, ["intensity"])
    b = CpuRenderer(cfg, f.capacity, ["intensity"])
    a.render(f, terrain_camera())
    b.render(f, terrain_camera())
    img = a.read_image()
    a.render(f, terrain_camera())
    assert (img == b.read_image()).all() and (img == a.read_image()).all()
    assert (img != img[0, 0]).any(axis=-1).mean() > 0.1  # the scene is actually there


def test_importance_sampling_frequency_follows_normalised_importance():
    n = 4000
    imp = np.tile(np.array([0.0, 0.25, 0.5, 1.0], np.float32), n // 4)
    pts = np.zeros((n, 3))
    cfg = render_cfg(size=[8, 8], importance_sampling=True)
    kept = np.zeros(4)
    for seed in range(50):
        f = make_frame(pts, importance=imp, seed=seed)
        sel = select_points(f, CAM, cfg, 8, 8)
        kept += np.bincount(sel.logical % 4, minlength=4)
    freq = kept / (50 * n / 4)
    assert abs(freq[0]) < 0.001 and abs(freq[1] - 0.25) < 0.02 and abs(freq[2] - 0.5) < 0.02 and freq[3] == 1.0


def test_pick_front_point_and_hidpi():
    cfg = render_cfg(size=[32, 32], point_size=4, pick_radius=2)
    f = make_frame([[0, 0, 0.0], [0, 0, 2.0], [3, 3, 0]], capacity=4, head=1)  # slots 1, 2, 3
    r = CpuRenderer(cfg, 4, ["intensity"])
    r.render(f, CAM)
    assert r.pick(16, 16) == 2                  # the nearer of the two stacked points
    assert r.pick(8, 8, pixel_ratio=2.0) == 2   # window (8, 8) at 2x is pixel (16, 16)
    assert r.pick(1, 30) is None                # nothing within the radius
    assert r.pick(-100, 5) is None


def test_selection_matches_wgpu_reference_rules():
    from pointflow.render.wgpu_tier import reference as R
    w = terrain(20_000, seed=4)
    imp = np.abs(np.sin(w[:, 1])).astype(np.float32)
    f = make_frame(w, capacity=25_000, head=21_000, importance=imp, t_ms=np.linspace(0, 900, len(w)),
                   now_ms=1000.0, seed=9)
    cfg = render_cfg(size=[320, 240], time_window_ms=600.0, lod_stride=2, importance_sampling=True)
    cam = terrain_camera()
    sel = select_points(f, cam, cfg, 320, 240)
    occ = f.occupied_slots()
    keep = R.keep_mask(f.positions, f.head, f.size, f.capacity, cam.frustum_planes(320, 240, f.origin),
                       t_ingest_ms=f.t_ingest_ms, now_ms=f.now_ms, window_ms=600.0, lod_stride=2,
                       importance=f.importance, importance_range=(float(imp.min()), float(imp.max())), frame_seed=9)
    assert set(np.flatnonzero(keep)) == set(sel.slots.tolist())
    f.budget = sel.n // 3
    sel_b = select_points(f, cam, cfg, 320, 240)
    u = R.uniform01(sel.slots, R.budget_seed(9))
    expect = sel.slots[u < R.budget_fraction(f.budget, sel.n)][: f.budget]
    assert set(expect.tolist()) == set(sel_b.slots.tolist()) and 0 < sel_b.n <= f.budget
    assert occ.size == f.size


def test_importance_range_for_budget_hits_the_budget_in_expectation():
    from pointflow.render.rules import importance_range_for_budget, keep_probability
    rng = np.random.default_rng(0)
    imp = rng.uniform(0, 1, 100_000).astype(np.float32) ** 3  # mean p = 0.25
    for budget in (5_000, 50_000, 90_000):
        lo, hi = importance_range_for_budget(imp, 0.0, 1.0, budget)
        expected = keep_probability(imp, lo, hi).sum()
        assert abs(expected - budget) / budget < 0.01
