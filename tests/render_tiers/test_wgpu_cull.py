"""Batch culling in the wgpu tier (issue 41), both raster methods: the passes over points walk
only the runs of the ring between culled whole batches, and the image, the counters and the
automatic colour range are those without culling, byte for byte: across the ring's wrap with
the head inside a batch, over a ring split in chunks, with a budget, and on a ring rewritten
between frames (dirty ranges, one wrapping)."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import draw
from gpu_util import require_adapter
from scenes import make_frame, render_cfg, terrain

import pointflow.render.batches as batches
from pointflow.render.base import FrameInput
from pointflow.render.camera import Camera
from pointflow.render.wgpu_tier import chunks

METHODS = ["compute", "quads"]
#: looks down at the x < 0 end of a terrain sorted by x
CAM = Camera(eye=[-35, -5, 40], target=[-35, 0, 0], near=1, far=200, fov_deg=40)
COUNTS = ("occupied", "removed_nonfinite", "survivors_before_budget")


@pytest.fixture(autouse=True)
def _small_batches(monkeypatch):
    monkeypatch.setattr(batches, "BATCH_SLOTS", 256)


def pair(monkeypatch, cfg, capacity, channels, **kw):
    """(culling on, culling off) renderers."""
    require_adapter()
    from pointflow.render.wgpu_tier import WgpuRenderer
    out = []
    for cull in ("1", "0"):
        monkeypatch.setenv(batches.ENV_CULL, cull)
        out.append(WgpuRenderer(cfg, capacity, list(channels), **kw))
    return out


def check_same(on, off, f, cam=CAM):
    """Draw ``f`` with both; same bytes, same counters, same survivors; the culled points."""
    a, sa = draw(on, f, cam)
    b, sb = draw(off, f, cam)
    assert np.array_equal(a, b)
    assert sa.drawn == sb.drawn
    for k in COUNTS:
        assert sa.extra[k] == sb.extra[k], k
    assert np.array_equal(on.debug_survivors(), off.debug_survivors())
    assert sb.extra["culled_points"] == 0
    return a, sa


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("chunked", [False, True])
@pytest.mark.parametrize("budget", [None, 200])
def test_batches_that_straddle_the_wrap_culled_or_not(monkeypatch, method, chunked, budget):
    """A ring whose occupied range wraps past the end, the head inside a batch (cut, never
    culled whole), points sorted by x so that a view of one end culls whole batches at the
    other; in one binding or in chunks (the chunk of the head walked twice), with
    and without a budget that bites: culling on and off draw the same."""
    w = terrain(5_000, seed=9)
    w = w[np.argsort(w[:, 0])]
    f = make_frame(w, capacity=5_300, head=5_300 - 1_000, intensity=np.linspace(0, 1, len(w), dtype=np.float32),
                   budget=budget)
    assert f.head + f.size > f.capacity and f.head % 256 != 0  # wraps; the head inside a batch
    cfg = render_cfg(size=[320, 240], point_size=3, raster=method)
    on, off = pair(monkeypatch, cfg, f.capacity, f.channels, max_binding=16 * 1_312 if chunked else None)
    try:
        assert (on.info()["chunks"] > 1) == chunked
        img, st = check_same(on, off, f)
        assert st.extra["culled_points"] > 1_000 and st.extra["runs"] >= 1
        assert (img != img[0, 0]).any(axis=-1).mean() > (0.05 if budget is None else 0.01), "no points in view"
        if budget is not None:
            assert st.drawn <= budget < st.extra["survivors_before_budget"]
    finally:
        on.close()
        off.close()


@pytest.mark.parametrize("method", METHODS)
def test_every_filter_keeps_the_whole_rings_indices(monkeypatch, method):
    """LOD stride, importance sampling, a time window, colour by ingest time and a budget:
    each run keeps its logical indices and slots (strides, hashes and ranks of the whole
    ring), so culling on and off draw the same."""
    w = terrain(6_000, seed=5)
    w = w[np.argsort(w[:, 0])]
    n = len(w)
    f = make_frame(w, capacity=6_500, head=6_500 - 2_000, intensity=np.linspace(0, 1, n, dtype=np.float32),
                   importance=np.random.default_rng(3).random(n).astype(np.float32),
                   t_ms=np.linspace(0, 1_000, n), now_ms=1_000.0, budget=40)
    cfg = render_cfg(size=[240, 180], point_size=3, raster=method, lod_stride=3, importance_sampling=True,
                     time_window_ms=900.0, color_by="ingest_time", color_range=[0.0, 1_000.0])
    on, off = pair(monkeypatch, cfg, f.capacity, f.channels)
    try:
        img, st = check_same(on, off, f)
        assert st.extra["culled_points"] > 1_000
        assert 0 < st.drawn <= 40 < st.extra["survivors_before_budget"]
    finally:
        on.close()
        off.close()


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("color_by", ["z", "intensity", "ingest_time"])
def test_culled_batches_keep_the_counts_and_the_automatic_colour_range(monkeypatch, method, color_by):
    """A culled batch touches no point on the GPU, yet the non-finite count, the occupied
    count and the automatic colour range (its top in the culled batches; z, a scalar channel,
    the ingest time; points without a finite position left out of it) are the whole ring's."""
    w = terrain(8_192, seed=13)
    w = w[np.argsort(w[:, 0])]
    w[7_000] = np.nan  # in a batch the view culls
    w[7_424:7_680] = np.inf  # a whole batch without a finite point
    inten = np.linspace(0, 1, len(w), dtype=np.float32) ** 2
    t = np.linspace(0.0, 5_000.0, len(w))
    v = {"z": w[:, 2], "intensity": inten, "ingest_time": t}[color_by]
    fin = np.isfinite(w).all(axis=1)
    assert v[fin].max() > v[:4_000][fin[:4_000]].max()  # the range's top lies in the culled batches
    f = make_frame(w, intensity=inten, t_ms=t, now_ms=5_000.0)
    assert not f.channel_ranges  # the ranges are reduced over the ring: automatic
    cfg = render_cfg(size=[200, 150], point_size=2, color_by=color_by, color_range="auto", raster=method)
    on, off = pair(monkeypatch, cfg, f.capacity, f.channels)
    try:
        _, st = check_same(on, off, f)
        assert st.extra["culled_points"] > 4_000
        assert st.extra["removed_nonfinite"] == 257 and st.extra["occupied"] == 8_192
    finally:
        on.close()
        off.close()


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("auto", [False, True])
def test_a_ring_rewritten_between_frames(monkeypatch, method, auto):
    """A ring rewritten frame after frame (partly, across the end: a dirty range (a, b) with
    b < a, then wholly), each write a band of x so that batches stay compact in space: every
    frame draws the same with culling on and off, and culling skips points. ``auto``: the
    intensity grows with x and shrinks with each write, so a culled batch's kept range that
    did not follow its rewrites would widen the automatic range (its top in culled batches)."""
    cap = 9_000
    rng = np.random.default_rng(12)
    pos = np.zeros((cap, 3), np.float32)
    inten = np.zeros(cap, np.float32)
    cfg = render_cfg(size=[200, 150], point_size=2, raster=method, color_by="intensity",
                     color_range="auto" if auto else [0.0, 1.0])
    cam = Camera(eye=[-15, -12, 10], target=[-15, 0, 0], near=1, far=100)

    def frame(head, size, dirty):
        return FrameInput(positions=pos, importance=np.zeros(cap, np.float32), t_ingest_ms=np.zeros(cap),
                          channels={"intensity": inten}, head=head, size=size, capacity=cap, origin=np.zeros(3),
                          now_ms=0.0, dirty=dirty)

    on, off = pair(monkeypatch, cfg, cap, ["intensity"])
    try:
        write, size, culled = 0, 0, []
        for k, n in enumerate((4_000, 3_000, 3_500, 2_000, cap, 1_000)):
            slots = (write + np.arange(n)) % cap
            x = np.sort(rng.uniform(-20, 20, n))  # each write sweeps x once: compact batches
            pos[slots] = np.column_stack([x, rng.uniform(-5, 5, n), rng.uniform(-1, 1, n)])
            inten[slots] = 10 / (k + 1) * (x + 20) / 40 + 0.01 * rng.random(n) if auto else rng.random(n)
            dirty = [(write, (write + n) % cap)] if n < cap else [(0, cap)]
            if k == 2:
                assert dirty[0][1] < dirty[0][0]  # the wrapping dirty range
            write = (write + n) % cap
            size = min(size + n, cap)
            f = frame((write - size) % cap, size, None if k == 0 else dirty)
            img, st = check_same(on, off, f, cam)
            assert (img != img[0, 0]).any(axis=-1).mean() > 0.02, f"frame {k}: the view must show points"
            culled.append(st.extra["culled_points"])
        assert min(culled) > 0, culled
    finally:
        on.close()
        off.close()


@pytest.mark.parametrize("head,size,cap,clen", [(4_300, 5_000, 5_300, 5_300), (4_300, 5_000, 5_300, 1_280),
                                                (0, 9_000, 9_000, 2_048), (8_900, 9_000, 9_000, 2_048)])
def test_runs_walk_every_unculled_logical_index_once_in_order(head, size, cap, clen):
    """chunks.runs: the segments less the culled ranges (any of them, including ones across a
    chunk's edge and the first and last) walk each other logical index once, in order, on
    its own slot, and the output windows fit their chunk."""
    table = chunks.chunks(cap, clen)
    segs = chunks.segments(head, size, cap, cap, table)
    if len(table) == 1:
        segs[0].size = size
    rng = np.random.default_rng(head + clen)
    for _ in range(20):
        edges = np.sort(rng.choice(np.arange(1, size), 12, replace=False))
        cut = [(int(a), int(b - a)) for a, b in zip(edges[0::2], edges[1::2])]
        if rng.random() < 0.3:
            cut = [(0, 300)] + [c for c in cut if c[0] > 300]
        runs = chunks.runs(segs, [a for a, _ in cut], [n for _, n in cut], len(segs),
                           [n + chunks.OUT_ALIGN for _, n in table])
        assert runs is not None
        want = np.ones(size, bool)
        for a, n in cut:
            want[a:a + n] = False
        logical = np.concatenate([r.logical_base + np.arange(r.size) for r in runs])
        assert np.array_equal(logical, np.flatnonzero(want))
        slots = np.concatenate([r.slot_base + (r.head + np.arange(r.size)) % r.capacity for r in runs])
        assert np.array_equal(slots, (head + logical) % cap)
        assert [r.index for r in runs] == list(range(len(segs), len(segs) + len(runs)))
        for r in runs:
            assert r.out_off % chunks.OUT_ALIGN == 0 and r.out_off + r.size <= table[r.chunk][1] + chunks.OUT_ALIGN
