"""Footprint LOD (``render.lod_fill``, issue 41: LOD picks by batch, as the map layer picks
nodes). One function (render/batches.py ``lod_masks``) turns each batch's bounds into a
power-of-two stride; every tier applies it with the same per-slot test, so every tier draws
the points the numpy reference keeps: across the ring's wrap, over a wgpu ring split in
chunks (slots offset by the chunk's base), and on a ring rewritten between frames."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from conftest import diff_fraction, draw
from gpu_util import require_adapter
from scenes import make_frame, render_cfg, terrain

from pointflow.config import ConfigError, load_config
from pointflow.render import batches
from pointflow.render.base import FrameInput
from pointflow.render.camera import Camera, project_to_pixels
from pointflow.render.cpu import CpuRenderer
from pointflow.render.rules import select_points
from pointflow.render.wgpu_tier.reference import keep_mask

B = batches.BATCH_SLOTS
#: a grazing view over a wide terrain: far batches cover few pixels for their points
CAM = Camera(eye=[0, -330, 40], target=[0, 0, 0], near=1, far=1000, fov_deg=50)


def _scene(n: int = 150_000, extra: int = 6_000, behind: int = 20_000) -> FrameInput:
    """A terrain in strips along y (a batch holds a few strips: near batches and far ones),
    in a ring whose occupied range wraps past its end with the head inside a batch
    (``behind`` slots before the end)."""
    w = terrain(n, seed=2, extent=300)
    w = w[np.lexsort((w[:, 0], w[:, 1] // 20))]
    cap = n + extra
    f = make_frame(w, capacity=cap, head=cap - behind)
    assert f.head + f.size > f.capacity and f.head % B != 0
    return f


def _stats(r, st):
    return (r.finish() or st) if hasattr(r, "finish") else st


def test_the_reference_thins_far_batches_and_keeps_near_ones():
    f = _scene()
    full = select_points(f, CAM, render_cfg(size=[320, 240]), 320, 240)
    lod = select_points(f, CAM, render_cfg(size=[320, 240], lod_fill=1.0), 320, 240)
    assert lod.counts["lod"] > full.counts["drawn"] // 3 and lod.counts["drawn"] < full.counts["drawn"]
    assert set(lod.slots.tolist()) <= set(full.slots.tolist())
    # a slot is dropped only by its batch's stride
    bb = batches.BatchBounds()
    bb.note(f)
    masks = bb.lod_masks(f, CAM, render_cfg(size=[320, 240], lod_fill=1.0), 320, 240)
    dropped = np.setdiff1d(full.slots, lod.slots)
    assert (dropped & masks[dropped // B].astype(np.int64)).all()
    assert not (lod.slots & masks[lod.slots // B].astype(np.int64)).any()
    # the batch nearest the eye keeps every point, the farthest is thinned
    near = np.argmin(bb.lo[:, 1])
    far = np.argmax(bb.hi[:, 1])
    assert masks[near] == 0 < masks[far]


def test_lod_off_changes_nothing():
    f = _scene(60_000)
    a = select_points(f, CAM, render_cfg(size=[320, 240]), 320, 240)
    b = select_points(f, CAM, render_cfg(size=[320, 240], lod_fill=0.0), 320, 240)
    assert np.array_equal(a.slots, b.slots) and b.counts["lod"] == 0


def test_strides_keep_about_fill_points_per_cell():
    """Checked against the reference projection (camera.project_to_pixels), not the
    function's own: a stride above 1 keeps at least ``fill`` points per point-sized cell of its
    box's rectangle on screen, and twice the stride would keep fewer (unless at the largest)."""
    rng = np.random.default_rng(4)
    W, H, px, fill = 640, 480, 2.0, 1.5
    vp = CAM.view_proj(W, H)
    lo = rng.uniform(-300, 300, (400, 3)) * [1, 1, 0.05] + [0, 200, 0]
    hi = lo + rng.uniform(0.5, 60, (400, 3))
    occ = rng.integers(2, B + 1, 400)
    masks = batches.lod_masks(lo, hi, occ, vp, W, H, px, 0.0, fill)
    s = masks.astype(np.int64) + 1
    assert ((s & (s - 1)) == 0).all() and s.max() <= batches.LOD_MAX_STRIDE and s.max() > 1
    for k in range(400):
        corners = np.array([[(hi if (c >> i) & 1 else lo)[k, i] for i in range(3)] for c in range(8)])
        x, y, _, w = project_to_pixels(corners, vp, W, H)
        if (w <= 0).any():
            assert s[k] == 1
            continue
        cells = max((x.max() - x.min()) * (y.max() - y.min()) / px ** 2, 1.0)
        if s[k] > 1:  # (stride 1: every point, however few)
            assert occ[k] / s[k] >= fill * cells * (1 - 1e-9)
        if s[k] < batches.LOD_MAX_STRIDE:
            assert occ[k] / (2 * s[k]) < fill * cells
    # a box reaching behind the eye, or without a finite point, keeps every slot
    eye = np.asarray(CAM.eye, float)
    m = batches.lod_masks(np.array([eye - 1, [np.inf] * 3]), np.array([eye + 1, [-np.inf] * 3]),
                          np.array([B, B]), vp, W, H, px, 0.0, 1.0)
    assert (m == 0).all()


def test_the_smallest_fills_thin_the_most_and_the_largest_not_at_all():
    """Extremes that pass validation: a subnormal fill (its stride overflows) thins the most,
    an infinite one keeps every slot."""
    vp = CAM.view_proj(320, 240)
    lo, hi, occ = np.array([[-10.0, 200.0, 0.0]]), np.array([[-5.0, 205.0, 5.0]]), np.array([B])
    assert batches.lod_masks(lo, hi, occ, vp, 320, 240, 2.0, 0.0, 1e-320)[0] == batches.LOD_MAX_STRIDE - 1
    assert batches.lod_masks(lo, hi, occ, vp, 320, 240, 2.0, 0.0, float("inf"))[0] == 0


def test_world_size_points_thin_less_when_bigger():
    """World-size points: a bigger point covers more pixels, so fewer are needed (sizes
    that stay above the 1 px clamp at the far batches)."""
    f = _scene()
    small = select_points(f, CAM, render_cfg(size=[320, 240], point_size_space="world", point_size=1.0,
                                             lod_fill=1.0), 320, 240)
    big = select_points(f, CAM, render_cfg(size=[320, 240], point_size_space="world", point_size=4.0,
                                           lod_fill=1.0), 320, 240)
    assert big.counts["lod"] > small.counts["lod"] > 0


def test_every_tier_draws_what_the_reference_keeps(make, tier):
    f = _scene()
    cfg = render_cfg(size=[320, 240], point_size=2, lod_fill=1.0)
    ref = CpuRenderer(cfg, f.capacity, list(f.channels))
    full = CpuRenderer(dataclasses.replace(cfg, lod_fill=0.0), f.capacity, list(f.channels))
    ref_img, ref_st = draw(ref, f, CAM)
    full_img, full_st = draw(full, f, CAM)
    assert ref_st.drawn < 0.8 * full_st.drawn and ref_st.extra["removed_lod"] > 0
    assert diff_fraction(ref_img, full_img) > 0.01  # the LOD shows
    r = make(cfg, f.capacity, list(f.channels))
    img, st = draw(r, f, CAM)
    st = _stats(r, st)
    assert st.drawn == ref_st.drawn
    assert diff_fraction(img, ref_img) <= 0.002, tier
    if tier.startswith("wgpu"):
        assert np.array_equal(r.debug_survivors(), np.sort(select_points(f, CAM, cfg, 320, 240).slots))


@pytest.mark.parametrize("color_by", ["intensity", "z"])
def test_dropped_slots_still_count_and_set_the_automatic_colour_range(make, tier, color_by):
    """Slots the LOD drops are never drawn, yet their non-finite positions are counted and
    their values belong to the automatic colour range (the tiers' fast loops skip their
    projection, not their reading): the extremes sit in dropped slots of the far batch."""
    f = _scene()
    cfg = render_cfg(size=[320, 240], point_size=2, lod_fill=1.0, color_by=color_by, color_range="auto")
    bb = batches.BatchBounds()
    bb.note(f)
    masks = bb.lod_masks(f, CAM, cfg, 320, 240)
    far = int(np.argmax(masks))
    assert masks[far] > 0
    slots = far * B + np.arange(1, 40, 2)  # odd slots: dropped by any stride
    occupied = (slots - f.head) % f.capacity < f.size
    slots = slots[occupied]
    f.channels["intensity"][slots[:5]] = [-50.0, 60.0, -50.0, 60.0, 60.0]
    f.positions[slots[5:10], 2] = [900.0, -900.0, 900.0, -900.0, 900.0]
    f.positions[slots[10:13]] = np.nan
    ref_img, ref_st = draw(CpuRenderer(cfg, f.capacity, list(f.channels)), f, CAM)
    r = make(cfg, f.capacity, list(f.channels))
    img, st = draw(r, f, CAM)
    st = _stats(r, st)
    assert ref_st.extra["removed_nonfinite"] == 3 and st.extra["removed_nonfinite"] == 3
    assert st.drawn == ref_st.drawn
    assert diff_fraction(img, ref_img) <= 0.002, tier
    # the extremes set the range: without them the picture's colours change
    g = dataclasses.replace(cfg, color_range=[-50.0, 60.0] if color_by == "intensity" else [-900.0, 900.0])
    fixed_img, _ = draw(CpuRenderer(g, f.capacity, list(f.channels)), f, CAM)
    assert np.array_equal(fixed_img, ref_img)


@pytest.mark.parametrize("split", ["points", "bins", "bands"])
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("style", ["squares", "world_round"])
def test_the_compiled_raster_draws_the_reference_bytes_in_every_split(monkeypatch, split, threads, style):
    """The compiled raster's lean loops (squares: blocks that gather a stride's kept slots or
    skip a small stride's stores) and its general loop (world-size round points), in every
    split and at 1 and 2 threads: the reference's image byte for byte and its drawn count;
    colour by z with the automatic range, non-finite points in dropped slots."""
    import numba  # (a core dependency: the compiled raster's kernels)

    from pointflow.render.cpu_compute import CpuComputeRenderer
    f = _scene()
    bad = (f.head + np.arange(10, f.size, 9_973)) % f.capacity
    f.positions[bad] = np.nan
    kw = dict(point_size_space="world", point_size=1.0, point_shape="round") if style == "world_round" else {}
    cfg = render_cfg(size=[320, 240], lod_fill=2.0, color_by="z", color_range="auto", **kw)
    monkeypatch.setenv("POINTFLOW_CPU_RASTER_SPLIT", split)
    monkeypatch.setenv("POINTFLOW_CPU_RASTER_ADAPTIVE", "0")
    n = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        r = CpuComputeRenderer(cfg, f.capacity, list(f.channels))
        img, st = draw(r, f, CAM)
        r.close()
    finally:
        numba.set_num_threads(n)
    ref_img, ref_st = draw(CpuRenderer(cfg, f.capacity, list(f.channels)), f, CAM)
    assert ref_st.extra["removed_lod"] > 10_000
    assert st.drawn == ref_st.drawn and st.extra["removed_nonfinite"] == ref_st.extra["removed_nonfinite"] > 0
    assert np.array_equal(img, ref_img)


@pytest.mark.parametrize("method", ["compute", "quads"])
def test_a_wgpu_ring_in_chunks_thins_by_the_whole_rings_slots(method):
    """Chunks of slots: a chunk's shader sees slots from 0, the masks index the whole ring's."""
    require_adapter()
    from pointflow.render.wgpu_tier import WgpuRenderer
    f = _scene()
    cfg = render_cfg(size=[320, 240], point_size=2, lod_fill=1.0, raster=method)
    r = WgpuRenderer(cfg, f.capacity, list(f.channels), max_binding=3 * B * 16)
    try:
        assert r.info()["chunks"] > 1
        draw(r, f, CAM)
        want = np.sort(select_points(f, CAM, cfg, 320, 240).slots)
        assert np.array_equal(r.debug_survivors(), want)
        # the same set by the wgpu tier's per-slot reference of its rules
        bb = batches.BatchBounds()
        bb.note(f)
        per_slot = keep_mask(f.positions, f.head, f.size, f.capacity, CAM.frustum_planes(320, 240, f.origin),
                             batch_lod=bb.lod_masks(f, CAM, cfg, 320, 240))
        assert np.array_equal(np.flatnonzero(per_slot), want)
    finally:
        r.close()


def test_a_ring_rewritten_between_frames(make, tier):
    """Frames rewrite part of the ring (a far strip moved near, dirty ranges, one wrapping):
    the strides follow the new bounds and every tier keeps drawing what the reference keeps."""
    f0 = _scene(100_000)
    cap = f0.capacity
    cfg = render_cfg(size=[240, 180], point_size=2, lod_fill=2.0)
    r = make(cfg, cap, list(f0.channels))
    ref = CpuRenderer(cfg, cap, list(f0.channels))
    pos, head = f0.positions, int(f0.head)
    drawn = []
    for k, n in enumerate((0, 30_000, 25_000)):
        pos = pos.copy()
        slots = (head + np.arange(n)) % cap
        pos[slots] = (terrain(n, seed=20 + k, extent=60) + [0, -200, 0]).astype(np.float32) if n else pos[slots]
        dirty = None if k == 0 else [(head, (head + n) % cap)]
        head = (head + n) % cap
        f = FrameInput(positions=pos, importance=f0.importance, t_ingest_ms=f0.t_ingest_ms, channels=f0.channels,
                       head=head, size=f0.size, capacity=cap, origin=f0.origin, now_ms=0.0, dirty=dirty)
        ref_img, ref_st = draw(ref, f, CAM)
        img, st = draw(r, f, CAM)
        assert _stats(r, st).drawn == ref_st.drawn, f"frame {k}"
        assert diff_fraction(img, ref_img) <= 0.002, f"frame {k}"
        drawn.append(ref_st.drawn)
    assert len(set(drawn)) == 3  # the rewrites changed what LOD keeps
    ref.close()


def test_a_negative_fill_is_refused_naming_the_key():
    with pytest.raises(ConfigError, match="render.lod_fill"):
        load_config({"source": {"transport": "synthetic"}, "render": {"lod_fill": -1}})


@pytest.mark.parametrize("tier", ["wgpu-compute", "wgpu-quads", "cpu-compute"])
@pytest.mark.parametrize("color_by", ["intensity", "ingest_time"])
def test_thinned_batches_the_cpu_counts_are_not_read_yet_count(make, tier, color_by):
    """A thinned batch whose slots are all occupied takes its non-finite count and its share
    of the automatic colour range from its bounds (``batches.LOD_CPU_COUNTED``: the wgpu
    tier's ``Culling.lod_counted``, the compiled tier's batch stats), so the passes and lean
    loops skip its dropped slots without reading them. The counts and colours stay the
    reference's with the extremes and non-finite points in such slots, and follow a rewrite
    of that batch (dirty range)."""
    f = _scene(behind=20_001)  # odd: the workgroups' ranges start between kept slots
    f.t_ingest_ms = np.linspace(0.0, 5_000.0, f.capacity)
    cfg = render_cfg(size=[320, 240], point_size=2, lod_fill=1.0, color_by=color_by, color_range="auto")
    bb = batches.BatchBounds()
    bb.note(f)
    masks = bb.lod_masks(f, CAM, cfg, 320, 240)
    k = np.arange(masks.size)
    whole = batches.occupied_per_batch(f.head, f.size, f.capacity) == np.minimum((k + 1) * B, f.capacity) - k * B
    cand = np.flatnonzero((masks > 0) & whole)
    far = int(cand[np.argmax(masks[cand])])
    slots = far * B + np.arange(1, 40, 2)  # odd slots: dropped by any stride
    values = f.t_ingest_ms if color_by == "ingest_time" else f.channels["intensity"]
    before = values[slots[:4]].copy()
    values[slots[:4]] = [-50.0, 9_000.0, -50.0, 9_000.0]
    f.positions[slots[10:13]] = np.nan
    ref = CpuRenderer(cfg, f.capacity, list(f.channels))
    r = make(cfg, f.capacity, list(f.channels))
    for step in ("extremes", "rewritten"):
        ref_img, ref_st = draw(ref, f, CAM)
        img, st = draw(r, f, CAM)
        assert st.extra["lod_cpu_counted_batches"] >= 1, step
        st = _stats(r, st)
        assert st.extra["occupied"] == f.size, step
        assert st.extra["removed_nonfinite"] == ref_st.extra["removed_nonfinite"] == (3 if step == "extremes" else 1)
        assert st.drawn == ref_st.drawn, step
        assert diff_fraction(img, ref_img) <= 0.002, step
        fixed = dataclasses.replace(cfg, color_range=[-50.0, 9_000.0])
        fixed_img, _ = draw(CpuRenderer(fixed, f.capacity, list(f.channels)), f, CAM)
        # with the extremes the range is theirs; rewritten without them it is not
        assert np.array_equal(fixed_img, ref_img) == (step == "extremes"), step
        values[slots[:4]] = before
        f.positions[slots[10:12]] = f.positions[slots[14:16]]
        f.dirty = [(far * B, far * B + B)]
    ref.close()


@pytest.mark.parametrize("method", ["compute", "quads"])
@pytest.mark.parametrize("chunked", [False, True])
@pytest.mark.parametrize("budget", [None, 20_000])
def test_the_wgpu_passes_walk_kept_slots_only_in_chunks_and_under_a_budget(method, chunked, budget):
    """The compute method walks a CPU-counted batch at its stride (its dropped slots get no
    thread; workgroups split where a batch ends and the slots wrap): in one binding or in
    chunks, with a budget that bites (ranks in logical order) or none, it keeps the
    reference's slots, and every occupied slot is counted once."""
    require_adapter()
    from pointflow.render.wgpu_tier import WgpuRenderer
    f = _scene(behind=20_001)  # odd: the workgroups' ranges start between kept slots
    f.budget = budget
    cfg = render_cfg(size=[320, 240], point_size=2, lod_fill=1.0, raster=method)
    r = WgpuRenderer(cfg, f.capacity, list(f.channels), max_binding=3 * B * 16 if chunked else None)
    try:
        assert (r.info()["chunks"] > 1) == chunked
        img, st = draw(r, f, CAM)
        assert st.extra["lod_cpu_counted_batches"] >= 3
        st = _stats(r, st)
        ref_img, ref_st = draw(CpuRenderer(cfg, f.capacity, list(f.channels)), f, CAM)
        assert st.extra["occupied"] == f.size
        assert st.drawn == ref_st.drawn
        if budget is not None:
            assert st.drawn <= budget < st.extra["survivors_before_budget"]
        assert diff_fraction(img, ref_img) <= 0.002
        assert np.array_equal(r.debug_survivors(), np.sort(select_points(f, CAM, cfg, 320, 240).slots))
    finally:
        r.close()


def test_only_whole_thinned_batches_are_countable_and_none_past_the_flags_bit():
    """``batches.lod_countable``: a thinned batch qualifies only with every slot occupied (a
    ring not yet full, the head's batch cut), and no batch does in a ring so large that a
    slot index could reach ``LOD_CPU_COUNTED``'s bit."""
    masks = np.array([3, 0, 7, 1], np.uint32)
    cap = 3 * B + 100  # the last batch holds 100 slots
    assert batches.lod_countable(masks, 0, cap, cap).tolist() == [True, False, True, True]
    # 2.5 batches occupied from slot B // 2: batch 0 cut, 1 and 2 whole, 3 empty
    assert batches.lod_countable(masks, B // 2, 2 * B + B // 2, cap).tolist() == [False, False, True, False]
    big = batches.LOD_CPU_COUNTED + 1
    assert not batches.lod_countable(masks, 0, big, big).any()
