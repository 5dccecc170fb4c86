"""Importance sampling, time window and point budget on the GPU."""
import numpy as np
import pytest

from pointflow.render.camera import Camera
from pointflow.render.wgpu_tier.reference import budget_fraction, budget_seed, keep_mask, uniform01

from .helpers import cfg, frame

pytestmark = pytest.mark.gpu

CAM = Camera(eye=[0.0, -20.0, 0.0], target=[0.0, 0.0, 0.0], near=1.0, far=100.0)


def _grid(n):
    rng = np.random.default_rng(3)
    return rng.uniform(-3, 3, size=(n, 3))


def test_importance_sampling_frequencies_chi_square(make_renderer):
    """Keep-frequency over many seeds is proportional to the normalised importance."""
    n, frames, levels = 2000, 150, 10
    imp = np.repeat(np.linspace(0.1, 1.0, levels), n // levels).astype(np.float32) * 4.0 + 2.0  # range [2, 6]
    r = make_renderer(cfg(importance_sampling=True), n)
    kept = np.zeros(n)
    for seed in range(frames):
        r.render(frame(_grid(n), importance=imp, ranges={"importance": (2.0, 6.0)}, seed=seed), CAM)
        kept[r.debug_survivors()] += 1
    p = (imp - 2.0) / 4.0
    groups = np.repeat(np.arange(levels), n // levels)
    obs = np.bincount(groups, weights=kept)
    exp = np.bincount(groups, weights=p * frames)
    var = np.bincount(groups, weights=frames * p * (1 - p))
    chi2 = float((((obs - exp) ** 2) / np.maximum(var, 1e-9))[var > 0].sum())
    # 9 groups with variance (p=1 has none): chi-square(9) 99.9th percentile = 27.9
    assert chi2 < 27.9, (chi2, obs / exp)
    assert obs[-1] == exp[-1]                      # importance at the top of the range: always kept
    assert abs(obs[0] / exp[0] - 1) < 0.1


def test_importance_sampling_matches_reference_and_degenerate_range(make_renderer):
    n = 5000
    imp = np.random.default_rng(4).uniform(0, 1, n).astype(np.float32)
    r = make_renderer(cfg(importance_sampling=True), n)
    f = frame(_grid(n), importance=imp, ranges={"importance": (0.0, 1.0)}, seed=77)
    r.render(f, CAM)
    want = np.flatnonzero(keep_mask(f.positions, 0, n, n, CAM.frustum_planes(320, 240), importance=f.importance,
                                    importance_range=(0.0, 1.0), frame_seed=77))
    assert np.array_equal(r.debug_survivors(), want)      # bit-identical hash on GPU and in numpy
    # all-equal importance: degenerate range -> normalised 1.0 -> everything kept
    r.render(frame(_grid(n), importance=np.full(n, 0.3, np.float32), ranges={"importance": (0.3, 0.3)}), CAM)
    assert r.debug_counts()["instance_count"] == n


def test_time_window_inclusive_at_large_epoch_offsets(make_renderer):
    now = 5 * 3600e3 + 0.25          # five hours into the run: float32 alone has 2 ms steps here
    win = 100.0
    t = np.array([now, now - win, now - win - 0.01, now - win + 0.01, now - 10 * win, now + 5.0])
    pts = np.zeros((len(t), 3))
    r = make_renderer(cfg(time_window_ms=win), len(t))
    r.render(frame(pts, t_ms=t, now_ms=now), CAM)
    assert r.debug_survivors().tolist() == [0, 1, 3, 5]
    off = make_renderer(cfg(time_window_ms=0.0), len(t))   # 0 = off
    off.render(frame(pts, t_ms=t, now_ms=now), CAM)
    assert off.debug_counts()["instance_count"] == len(t)


def test_budget_is_honoured_and_deterministic(make_renderer):
    n = 20_000
    r = make_renderer(cfg(), n)
    pts = _grid(n)
    r.render(frame(pts, budget=2000, seed=5), CAM)
    a = r.debug_survivors()
    c = r.debug_counts()
    assert c["culled"] == n
    assert 1700 <= len(a) <= 2000 and c["instance_count"] == len(a)
    u = uniform01(a, budget_seed(5))                        # the documented thinning rule
    assert (u < budget_fraction(2000, n)).all()
    assert len(np.unique(a)) == len(a)
    r.render(frame(pts, budget=2000, seed=5), CAM)
    assert np.array_equal(r.debug_survivors(), a)          # same seed, same points
    r.render(frame(pts, budget=2000, seed=6), CAM)
    assert not np.array_equal(r.debug_survivors(), a)
    r.render(frame(pts, budget=n * 2, seed=5), CAM)        # budget above the survivors: all drawn
    assert r.debug_counts()["instance_count"] == n
    r.render(frame(pts, budget=0), CAM)
    assert r.debug_counts()["instance_count"] == 0
    img = r.read_image()
    assert (img == img[0, 0]).all()
    r.render(frame(pts, budget=None), CAM)                 # back to no budget
    assert r.debug_counts()["instance_count"] == n


def test_budget_applies_after_culling(make_renderer):
    n = 20_000
    pts = _grid(n)
    pts[: n // 2, 1] -= 1000.0                  # half the points behind the camera
    r = make_renderer(cfg(), n)
    r.render(frame(pts, budget=5000, seed=1), CAM)
    got = r.debug_survivors()
    assert (got >= n // 2).all()
    assert 4600 <= len(got) <= 5000             # budget spent on visible points only
