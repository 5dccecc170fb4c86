"""Whole batches culled before any point is read (issue 41, render/batches.py) in the numpy
reference and the gl tier: the same image byte for byte and the same counts with culling on
and off, across a ring that wraps with its head inside a batch, and on a ring rewritten
between frames (dirty ranges, a wrapping one among them). The compiled cpu raster's own
batches are tested in test_cpu_threads.py."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import draw, tier_class
from scenes import make_frame, render_cfg, terrain

import pointflow.render.batches as batches
from pointflow.render.base import FrameInput
from pointflow.render.batches import BatchBounds, boxes_outside
from pointflow.render.camera import Camera

TIERS = ["cpu", "gl"]
#: looks straight down at the x < 0 end of a terrain sorted by x: whole batches at the other end
CAM = Camera(eye=[-35, -5, 40], target=[-35, 0, 0], near=1, far=200, fov_deg=40)


@pytest.fixture(autouse=True)
def _small_batches(monkeypatch):
    monkeypatch.setattr(batches, "BATCH_SLOTS", 256)


def _draw_both(monkeypatch, tier, cfg, frames, cam=CAM):
    """Images and stats of every frame, culling on then off (a renderer each)."""
    out = {}
    for cull in ("1", "0"):
        monkeypatch.setenv("POINTFLOW_CPU_RASTER_CULL", cull)
        r = tier_class(tier)(cfg, frames[0].capacity, list(frames[0].channels))
        try:
            out[cull] = [draw(r, f, cam) for f in frames]
        finally:
            r.close()
    return out


def _counts(st):
    return {k: v for k, v in st.extra.items() if k.startswith("removed_")}, st.drawn


@pytest.mark.parametrize("tier", TIERS)
def test_a_wrapping_ring_culled_or_not(monkeypatch, tier):
    """The occupied range wraps past the ring's end and the head sits inside a batch (that
    batch is never culled whole); a non-finite point in a culled batch still counts."""
    w = terrain(5_000, seed=9)
    w = w[np.argsort(w[:, 0])]
    w[4_500] = np.nan
    f = make_frame(w, capacity=5_300, head=5_300 - 1_000, intensity=np.linspace(0, 1, len(w), dtype=np.float32))
    assert f.head + f.size > f.capacity and f.head % 256 != 0
    cfg = render_cfg(size=[320, 240], point_size=3, color_by="z")
    out = _draw_both(monkeypatch, tier, cfg, [f])
    (on, s_on), (off, s_off) = out["1"][0], out["0"][0]
    assert (on != on[0, 0]).any(axis=-1).mean() > 0.05, "the view must show points"
    assert np.array_equal(on, off)
    assert _counts(s_on) == _counts(s_off) and s_on.extra["removed_nonfinite"] == 1
    assert s_on.extra["culled_points"] > 2_000 and s_off.extra["culled_points"] == 0
    # the batch the head cuts is not among the culled ones
    b = BatchBounds()
    b.note(f)
    ks, _ = b.culled(f, CAM.frustum_planes(320, 240, f.origin))
    assert f.head // 256 not in set(ks.tolist()) and ks.size > 0


@pytest.mark.parametrize("tier", TIERS)
def test_a_ring_rewritten_between_frames(monkeypatch, tier):
    """Frame after frame part of the ring is rewritten (announced in the dirty ranges, one of
    them wrapping past the end): culled or not, every frame is the same image."""
    cap = 6_000
    rng = np.random.default_rng(3)
    w = terrain(cap, seed=4)
    w = w[np.argsort(w[:, 0])]
    pos = w.astype(np.float32)
    frames, write = [], 0
    for k, n in enumerate((0, 2_000, 3_000, 2_500)):
        pos = pos.copy()
        slots = (write + np.arange(n)) % cap
        # new points, sorted by x and shifted: a batch culled last frame may come into view
        new = terrain(n, seed=10 + k) + [rng.uniform(-20, 20), 0, 0] if n else np.zeros((0, 3))
        pos[slots] = new[np.argsort(new[:, 0])].astype(np.float32)
        dirty = None if k == 0 else [(write, (write + n) % cap)]
        write = (write + n) % cap
        frames.append(FrameInput(positions=pos, importance=np.zeros(cap, np.float32), t_ingest_ms=np.zeros(cap),
                                 channels={"intensity": np.linspace(0, 1, cap, dtype=np.float32)}, head=write,
                                 size=cap, capacity=cap, origin=np.zeros(3), now_ms=0.0, dirty=dirty))
    assert any(f.dirty and f.dirty[0][1] < f.dirty[0][0] for f in frames)  # one wraps
    cfg = render_cfg(size=[240, 180], point_size=2)
    out = _draw_both(monkeypatch, tier, cfg, frames)
    for k in range(len(frames)):
        assert np.array_equal(out["1"][k][0], out["0"][k][0]), f"frame {k}"
        assert _counts(out["1"][k][1]) == _counts(out["0"][k][1]), f"frame {k}"
    assert all(st.extra["culled_points"] > 0 for _, st in out["1"]), [st.extra["culled_points"] for _, st in out["1"]]


def test_a_box_touching_a_plane_is_kept():
    """A box whose corner lies exactly on a plane (a point there is kept: inside is >= 0) is
    not outside; one clearly beyond it is; a box of non-finite points is not 'outside' (the
    caller culls it by its count)."""
    planes = np.array([[1.0, 0.0, 0.0, 0.0]])  # x >= 0 inside
    lo = np.array([[-2.0, 0, 0], [-2.0, 0, 0], [np.inf] * 3])
    hi = np.array([[0.0, 1, 1], [-1e-3, 1, 1], [-np.inf] * 3])
    assert boxes_outside(lo, hi, planes).tolist() == [False, True, False]


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.dtype(">f4")])
def test_bounds_reduced_in_runs_match_each_batch_alone(monkeypatch, dtype):
    """``BatchBounds.refresh`` reduces runs of consecutive whole batches together (a scratch
    of at most RUN_BATCHES batches): the bounds, non-finite counts and staleness are those of
    each batch's finite points reduced alone, with NaN, +-inf and -0.0 among them, a last
    partial batch, batches chosen out of order and with gaps, and runs longer than the
    scratch."""
    monkeypatch.setattr(batches, "RUN_BATCHES", 3)
    rng = np.random.default_rng(7)
    B, cap = 16, 16 * 11 + 5
    pos = (rng.standard_normal((cap, 3)) * 1e3).astype(dtype)
    pos[3, 1], pos[40, 0], pos[41, 2], pos[170, 1] = np.nan, np.inf, -np.inf, np.nan
    pos[64:80] = np.nan  # batch 4: no finite point
    pos[100, :] = -0.0  # batch 6: -0.0 an extreme
    pos[96:112, 0] = np.abs(pos[96:112, 0])
    f = FrameInput(positions=pos, importance=np.zeros(cap, np.float32), t_ingest_ms=np.zeros(cap),
                   channels={}, head=0, size=cap, capacity=cap, origin=np.zeros(3), now_ms=0.0)
    bb = BatchBounds(B)
    bb.note(f)
    ks = np.array([9, 0, 1, 2, 3, 4, 5, 6, 7, 11], np.int64)
    bb.refresh(pos, ks)
    for k in range(bb.lo.shape[0]):
        p = np.asarray(pos[k * B:min((k + 1) * B, cap)], np.float64)
        fin = np.isfinite(p).all(axis=1)
        if k not in ks:
            assert bb.stale[k] and np.isinf(bb.lo[k]).all(), k
            continue
        assert not bb.stale[k] and bb.bad[k] == int((~fin).sum()), k
        lo, hi = (p[fin].min(axis=0), p[fin].max(axis=0)) if fin.any() else ([np.inf] * 3, [-np.inf] * 3)
        assert np.array_equal(bb.lo[k], lo) and np.array_equal(bb.hi[k], hi), k
    assert bb.bad[4] == B and np.signbit(bb.lo[6, 0]) == np.signbit(pos[96:112, 0].min())
    pos[64:80] = 1.5  # rewritten finite: its count and bounds follow
    bb.stale[4] = True
    bb.refresh(pos, np.array([4], np.int64))
    assert bb.bad[4] == 0 and bb.lo[4].tolist() == [1.5] * 3 and bb.hi[4].tolist() == [1.5] * 3
