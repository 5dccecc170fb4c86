"""Compact positions in the wgpu tier's compute method (issue 41): positions relative to their
batch's box in 30 bits per axis over three words, the raster pass reading 1, 2 or 3 words per
batch as the view's pixel footprint allows (or the float32 positions). The image stays within
the agreement tests' bound (1% of pixels) of the full-precision path on georeferenced scenes;
a batch across the ring's wrap, a ring rewritten while drawn (bounds change: the batch encoded
again), a near view (fine level) and a far one (coarse) are covered."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from conftest import diff_fraction, draw
from gpu_util import require_adapter
from scenes import GEO, SCENES, make_frame, render_cfg, terrain

import pointflow.render.batches as batches
from pointflow.render.base import FrameInput
from pointflow.render.camera import Camera
from pointflow.render.cpu import CpuRenderer
from pointflow.render.wgpu_tier import compact

#: the agreement tests' bound (test_agreement.py)
BOUND = 0.01


@pytest.fixture(autouse=True)
def _encode_at_once(monkeypatch):
    """These tests check the words and levels: every written batch encoded at once (settling
    is tested on its own below)."""
    monkeypatch.setenv(compact.ENV_SETTLE, "0")


def pair(monkeypatch, cfg, capacity, channels, **kw):
    """(compact, full precision) compute-method renderers."""
    require_adapter()
    from pointflow.render.wgpu_tier import WgpuRenderer
    out = []
    for on in ("1", "0"):
        monkeypatch.setenv(compact.ENV_COMPACT, on)
        out.append(WgpuRenderer(dataclasses.replace(cfg, raster="compute"), capacity, list(channels), **kw))
    assert out[0].info()["compact_positions"] and not out[1].info()["compact_positions"]
    return out


def compare(a, b, f, cam):
    """Draw ``f`` with both; the images within the bound; (image, compact stats)."""
    ia, sa = draw(a, f, cam)
    ib, sb = draw(b, f, cam)
    assert (ib != ib[0, 0]).any(axis=-1).mean() > 0.05, "the scene must cover the image"
    d = diff_fraction(ia, ib)
    assert d <= BOUND, f"compact differs from full precision in {d:.2%} of pixels"
    assert "compact_levels" in sa.extra and "compact_levels" not in sb.extra
    return ia, ib, sa


def far_terrain(n=20_000, seed=1, off=(3_000.0, -2_000.0, 0.0)):
    """Terrain 3.6 km from a UTM-like ring origin: float32 origin-relative coordinates of a
    few thousand metres (their rounding is what compact levels must not make worse)."""
    w = terrain(n, seed=seed) + GEO + np.asarray(off)
    return w, GEO + np.asarray(off)


@pytest.mark.parametrize("color_by", ["z", "intensity"])
def test_georeferenced_scene_within_the_agreement_bound(monkeypatch, color_by):
    """Large coordinates (origin at a UTM-like position, points 3.6 km from it): compact and
    full precision agree within the bound, and both with the cpu reference; the compact path
    reads fewer than 12 bytes of position per point."""
    w, centre = far_terrain()
    # a full ring (slots never written hold zeros, i.e. the origin, and widen their batch's box)
    f = make_frame(w, origin=GEO, head=7_000, intensity=np.linspace(0, 1, len(w), dtype=np.float32))
    cam = Camera.fit([-50, -50, -4], [50, 50, 12], aspect=4 / 3).translated(centre)
    kw = dict(color_by="z", color_range="auto", colormap="grayscale") if color_by == "z" else {}
    cfg = render_cfg(size=[320, 240], point_size=3, **kw)
    a, b = pair(monkeypatch, cfg, f.capacity, f.channels)
    try:
        ia, ib, st = compare(a, b, f, cam)
        assert st.extra["compact_position_bytes_per_point"] < 12
        assert st.extra["compact_levels"]["float32"] == 0
        ref, _ = draw(CpuRenderer(cfg, f.capacity, list(f.channels)), f, cam)
        assert diff_fraction(ia, ref) <= BOUND
        assert a.info()["compact_levels"] == st.extra["compact_levels"]
    finally:
        a.close()
        b.close()


def test_batch_across_the_wrap_and_non_finite_points(monkeypatch):
    """Small batches, a ring whose occupied range wraps with the head inside a batch, a few
    non-finite positions (bit 31 of the coarse word): the same image within the bound, the
    same non-finite count; with every batch forced to the fine level, the image of the
    full-precision path (30 bits relative to a box are as fine as float32)."""
    monkeypatch.setattr(batches, "BATCH_SLOTS", 256)
    w, centre = far_terrain(5_000, seed=9)
    w = w[np.argsort(w[:, 0])]
    w[[10, 4_000]] = np.nan
    f = make_frame(w, origin=GEO, capacity=5_300, head=5_300 - 1_000,
                   intensity=np.linspace(0, 1, len(w), dtype=np.float32))
    assert f.head + f.size > f.capacity and f.head % 256 != 0
    cam = Camera.fit([-50, -50, -4], [50, 50, 12], aspect=4 / 3).translated(centre)
    cfg = render_cfg(size=[320, 240], point_size=3)
    a, b = pair(monkeypatch, cfg, f.capacity, f.channels)
    try:
        assert a._compact.batch == 256
        ia, ib, st = compare(a, b, f, cam)
        b.finish()
        assert st.extra["removed_nonfinite"] == 2 == b.finish().extra["removed_nonfinite"]
        a._compact_force = 3
        fine, _ = draw(a, f, cam)
        assert diff_fraction(fine, ib) <= 0.001
        a._compact_force = 1  # coarse everywhere: what the level choice avoids at this footprint
        coarse, _ = draw(a, f, cam)
        assert diff_fraction(coarse, ib) > diff_fraction(ia, ib)
    finally:
        a.close()
        b.close()


def test_ring_in_chunks(monkeypatch):
    """A ring split over several storage bindings (chunks of 1,280 slots, batches of 512: a
    batch across a chunk's edge, the chunk of the head walked twice): each chunk's words at
    its own slots, the batch table over the whole ring; within the bound, and at the fine
    level the float32 image."""
    monkeypatch.setattr(batches, "BATCH_SLOTS", 512)
    w, centre = far_terrain(6_000, seed=3)
    f = make_frame(w, origin=GEO, capacity=6_300, head=6_300 - 2_000, intensity=np.linspace(0, 1, 6_000, dtype=np.float32))
    cam = Camera.fit([-50, -50, -4], [50, 50, 12], aspect=4 / 3).translated(centre)
    cfg = render_cfg(size=[240, 180], point_size=3)
    a, b = pair(monkeypatch, cfg, f.capacity, f.channels, max_binding=12 * 1_290)
    try:
        assert a.info()["chunks"] > 1 and a.info()["chunk_slots"] % 512 != 0
        ia, ib, st = compare(a, b, f, cam)
        a._compact_force = 3
        assert diff_fraction(draw(a, f, cam)[0], ib) <= 0.001
    finally:
        a.close()
        b.close()


def rewrite(f: FrameInput, slots: np.ndarray, world: np.ndarray, head: int, size: int, dirty) -> FrameInput:
    pos = f.positions.copy()
    pos[slots] = (world - f.origin).astype(np.float32)
    return dataclasses.replace(f, positions=pos, head=head, size=size, dirty=dirty)


def test_ring_rewritten_while_drawn_encodes_changed_batches_again(monkeypatch):
    """Frames that rewrite parts of the ring (dirty ranges, one wrapping the end) and move
    points far out of their batch's box: the point buffers' encoding is redone for the changed batches,
    so the compact renderer fed frame after frame draws the bytes a fresh one draws, and
    stays within the bound of the full-precision path."""
    monkeypatch.setattr(batches, "BATCH_SLOTS", 512)
    require_adapter()
    from pointflow.render.wgpu_tier import WgpuRenderer
    w, centre = far_terrain(6_000, seed=4)
    f = make_frame(w, origin=GEO, capacity=6_000, head=0, intensity=np.linspace(0, 1, 6_000, dtype=np.float32))
    cam = Camera.fit([-60, -60, -4], [60, 60, 20], aspect=4 / 3).translated(centre)
    cfg = render_cfg(size=[240, 180], point_size=3)
    a, b = pair(monkeypatch, cfg, f.capacity, f.channels)
    rng = np.random.default_rng(5)
    try:
        compare(a, b, f, cam)
        steps = [(np.arange(1_000, 1_300), (1_000, 1_300)), (np.r_[5_800:6_000, 0:150], (5_800, 150)),
                 (np.arange(2_500, 2_520), (2_500, 2_520))]
        for i, (slots, rg) in enumerate(steps):
            new = centre + rng.uniform(-55, 55, (len(slots), 3)) * [1, 1, 0.2] + [0, 0, 10 + 3 * i]
            from pointflow.render.wgpu_tier.renderer import DATA_SETS
            before = a._compact.lo[a._frame_no % DATA_SETS].copy()
            f = rewrite(f, slots, new, head=int(slots[-1] + 1) % 6_000, size=6_000, dirty=[rg])
            ia, _, _ = compare(a, b, f, cam)
            s = (a._frame_no - 1) % DATA_SETS
            assert not np.array_equal(a._compact.lo[s], before), "the rewritten batches' boxes changed"
            monkeypatch.setenv(compact.ENV_COMPACT, "1")
            fresh = WgpuRenderer(dataclasses.replace(cfg, raster="compute"), f.capacity, list(f.channels))
            try:
                img, _ = draw(fresh, f, cam)
                assert np.array_equal(img, ia), f"step {i}: incremental encoding differs from a fresh one"
            finally:
                fresh.close()
    finally:
        a.close()
        b.close()


def test_new_origin_encodes_every_batch_again(monkeypatch):
    """A frame whose ring origin moved (every float32 position changed) though its dirty
    ranges name a few slots: every batch's box is reduced and encoded again, so the image is
    a fresh renderer's."""
    monkeypatch.setattr(batches, "BATCH_SLOTS", 512)
    require_adapter()
    from pointflow.render.wgpu_tier import WgpuRenderer
    w, centre = far_terrain(4_000, seed=6)
    f = make_frame(w, origin=GEO, intensity=np.linspace(0, 1, 4_000, dtype=np.float32))
    cam = Camera.fit([-60, -60, -4], [60, 60, 20], aspect=4 / 3).translated(centre)
    cfg = render_cfg(size=[240, 180], point_size=3)
    a, b = pair(monkeypatch, cfg, f.capacity, f.channels)
    try:
        compare(a, b, f, cam)
        org = GEO + [1_000.0, 500.0, 0.0]
        g = dataclasses.replace(f, positions=(w - org).astype(np.float32), origin=org, dirty=[(0, 10)])
        for _ in range(2):  # a second frame: nothing left to encode
            img, _, _ = compare(a, b, g, cam)
        monkeypatch.setenv(compact.ENV_COMPACT, "1")
        fresh = WgpuRenderer(dataclasses.replace(cfg, raster="compute"), f.capacity, list(f.channels))
        try:
            assert np.array_equal(draw(fresh, g, cam)[0], img)
        finally:
            fresh.close()
    finally:
        a.close()
        b.close()


def test_near_view_reads_fine_words_far_view_coarse(monkeypatch):
    """4 km of ground in batches of 256 points (a few hundred metres each, as a scanner's
    points arrive) seen from 2 m: fine words for the nearest batch; from 9 km: coarse, near 4
    bytes per point. Both within the bound of the full-precision path."""
    monkeypatch.setattr(batches, "BATCH_SLOTS", 256)
    rng = np.random.default_rng(2)
    n = 30_000
    w = np.column_stack([rng.uniform(0, 4_000, n), rng.uniform(-2_000, 2_000, n), rng.uniform(0, 50, n)])
    w = w[np.lexsort([w[:, 1] // 250, w[:, 0] // 250])] + GEO
    f = make_frame(w, origin=GEO, intensity=np.linspace(0, 1, n, dtype=np.float32))
    cfg = render_cfg(size=[320, 240], point_size=2)
    a, b = pair(monkeypatch, cfg, f.capacity, f.channels)
    try:
        near = Camera(eye=list(GEO + [-2.0, 0, 25]), target=list(GEO + [100.0, 0, 25]), near=0.5, far=5_000)
        _, _, st = compare(a, b, f, near)
        lv = st.extra["compact_levels"]
        assert lv["fine"] >= 1 and lv["medium"] > lv["coarse"], lv
        far = Camera(eye=list(GEO + [2_000.0, 0, 9_000]), target=list(GEO + [2_000.0, 0, 0]), near=100, far=20_000)
        _, _, st = compare(a, b, f, far)
        lv = st.extra["compact_levels"]
        assert lv["coarse"] >= 0.8 * sum(lv.values()) and lv["fine"] == lv["float32"] == 0, lv
        assert st.extra["compact_position_bytes_per_point"] < 5
    finally:
        a.close()
        b.close()


def test_quads_and_the_switch_keep_float32_positions(monkeypatch):
    """The quads method, POINTFLOW_WGPU_COMPACT=0, and (unset) a CPU adapter such as lavapipe
    draw from the float32 positions; info() says why."""
    require_adapter()
    from pointflow.render.wgpu_tier import WgpuRenderer
    monkeypatch.setenv(compact.ENV_COMPACT, "1")
    r = WgpuRenderer(render_cfg(raster="quads"), 100, ["intensity"])
    try:
        assert r.info()["compact_positions"] is False and "quads" in r.info()["compact_choice"]
    finally:
        r.close()
    monkeypatch.delenv(compact.ENV_COMPACT)
    r = WgpuRenderer(render_cfg(raster="compute"), 100, ["intensity"])
    try:
        cpu = r.adapter.info.get("adapter_type") == "CPU"
        assert r.info()["compact_positions"] is (not cpu), r.info()["compact_choice"]
    finally:
        r.close()
    assert compact.compact_choice("CPU")[0] is False and compact.compact_choice("DiscreteGPU")[0] is True


@pytest.mark.parametrize("scene", list(SCENES))
def test_agreement_scenes_match_the_cpu_reference(monkeypatch, scene):
    """Every agreement scene (test_agreement.py) drawn with compact positions stays within the
    bound of the cpu reference."""
    require_adapter()
    from pointflow.render.wgpu_tier import WgpuRenderer
    frame, cam, kw = SCENES[scene]()
    cfg = render_cfg(size=[320, 240], raster="compute", **kw)
    monkeypatch.setenv(compact.ENV_COMPACT, "1")
    r = WgpuRenderer(cfg, frame.capacity, list(frame.channels))
    try:
        img, st = draw(r, frame, cam)
        assert st.extra["compact_position_bytes_per_point"] < 12
        ref, _ = draw(CpuRenderer(cfg, frame.capacity, list(frame.channels)), frame, cam)
        assert diff_fraction(img, ref) <= BOUND
    finally:
        r.close()


def _decode(words: np.ndarray, lo: np.ndarray, ext: np.ndarray, level: int) -> np.ndarray:
    """The shader's decode in float64."""
    q = [np.stack([(wd >> s) & 1023 for s in (0, 10, 20)], axis=1).astype(np.float64) for wd in words]
    s1 = ext / 1024.0
    out = lo + q[0] * s1
    for i in range(1, level):
        out = out + q[i] * s1 / 1024.0 ** i
    return out + 0.5 * s1 / 1024.0 ** (level - 1)


def test_level_choice_bounds_the_move_in_pixels():
    """For boxes at many distances, the chosen level moves no decoded point by more than
    TOL_PX pixels (projected in float64); nearer boxes get finer levels."""
    rng = np.random.default_rng(0)
    cam = Camera(eye=[0, -30, 10], target=[0, 0, 0], near=0.5, far=1e6)
    vp = cam.view_proj(320, 240, None)
    seen = []
    for dist in (60.0, 600.0, 6_000.0, 60_000.0):
        c = np.array([0.0, dist, 0.0])
        p = c + rng.uniform(-1, 1, (2_000, 3)) * [40, 40, 5]
        lo, hi = p.min(axis=0), p.max(axis=0)
        lev = int(compact.choose_levels(lo[None], hi[None], vp, 320, 240)[0])
        assert lev in (1, 2, 3)
        words = compact.encode(p, np.broadcast_to(lo, p.shape), np.broadcast_to(hi - lo, p.shape))

        def px(x):
            h = np.column_stack([x, np.ones(len(x))]) @ vp.T
            return np.column_stack([h[:, 0] / h[:, 3] * 160, h[:, 1] / h[:, 3] * 120])

        move = np.abs(px(_decode(words, lo, hi - lo, lev)) - px(p)).max()
        assert move <= compact.TOL_PX * 1.001
        seen.append(lev)
    assert seen == sorted(seen, reverse=True) and len(set(seen)) >= 2, seen


def test_a_live_ring_reads_float32_until_its_batches_settle(monkeypatch):
    """Settling (compact.SETTLE_FRAMES): a batch is encoded only once no frame has written it
    for ``settle`` frames, at most ENCODE_POINTS_PER_FRAME points a frame; until then, and
    from the frame one of its slots is written again, it reads its float32 positions (level
    0). A ring that keeps writing one batch: that batch stays float32, the others settle two
    a frame; every frame within the bound of the full-precision path."""
    monkeypatch.setattr(batches, "BATCH_SLOTS", 512)
    monkeypatch.setenv(compact.ENV_SETTLE, "3")
    monkeypatch.setattr(compact, "ENCODE_POINTS_PER_FRAME", 2 * 512)
    w, centre = far_terrain(6_000, seed=4)
    f = make_frame(w, origin=GEO, capacity=6_000, head=0, intensity=np.linspace(0, 1, 6_000, dtype=np.float32))
    cam = Camera.fit([-60, -60, -4], [60, 60, 20], aspect=4 / 3).translated(centre)
    cfg = render_cfg(size=[240, 180], point_size=3)
    a, b = pair(monkeypatch, cfg, f.capacity, f.channels)
    nb = -(-6_000 // 512)
    rng = np.random.default_rng(8)
    try:
        ia, sa = draw(a, f, cam)
        ib, _ = draw(b, f, cam)
        assert sa.extra["compact_encoded_batches"] == 0 and sa.extra["compact_levels"]["float32"] == nb
        assert np.array_equal(ia, ib), "level 0 is the float32 path, byte for byte"
        encoded, seen = [], []
        for i in range(12):  # slots 0..99 of batch 0 rewritten every frame
            new = centre + rng.uniform(-55, 55, (100, 3)) * [1, 1, 0.2]
            f = rewrite(f, np.arange(100), new, head=100, size=6_000, dirty=[(0, 100)])
            ia, ib, st = compare(a, b, f, cam)
            encoded.append(st.extra["compact_encoded_batches"])
            seen.append(int(a._compact.levels[0]))
            newly = encoded[-1] - (encoded[-2] if i else 0)  # encoded this frame: their words uploaded
            assert 100 * 16 + max(newly - 1, 0) * 512 * 12 < st.uploaded_bytes <= 100 * 16 + newly * 512 * 12 \
                or (newly == 0 and st.uploaded_bytes == 100 * 16), (i, st.uploaded_bytes, encoded)
        # written in frame 0, encoded from frame 3 (loop index 2), two batches a frame, batch 0 never
        assert encoded[:2] == [0, 0] and encoded[2:5] == [2, 4, 6], encoded
        assert encoded[-1] == nb - 1 and set(seen) == {0}
        assert not a._compact.encoded[0][0] and a._compact.encoded[0][1:].all()
        assert (a._compact.levels[1:] > 0).any(), "settled batches read compact words"
        # a slot of a settled batch written again: float32 from that frame, settled again later
        k = 5
        new = centre + rng.uniform(-55, 55, (10, 3)) * [1, 1, 0.2]
        f = rewrite(f, np.arange(k * 512, k * 512 + 10), new, head=100, size=6_000, dirty=[(k * 512, k * 512 + 10)])
        _, _, st = compare(a, b, f, cam)
        assert a._compact.levels[k] == 0 and st.extra["compact_encoded_batches"] == nb - 2  # (not 0, not k)
        for _ in range(4):
            _, _, st = compare(a, b, dataclasses.replace(f, dirty=[]), cam)
        assert st.extra["compact_encoded_batches"] == nb  # everything settled: batch 0 too
        monkeypatch.setenv(compact.ENV_COMPACT, "1")
        monkeypatch.setenv(compact.ENV_SETTLE, "0")
        from pointflow.render.wgpu_tier import WgpuRenderer
        fresh = WgpuRenderer(dataclasses.replace(cfg, raster="compute"), f.capacity, list(f.channels))
        try:
            img, _ = draw(fresh, dataclasses.replace(f, dirty=None), cam)
            final, _ = draw(a, dataclasses.replace(f, dirty=[]), cam)
            assert np.array_equal(final, img), "settled words are the words encoded at once"
        finally:
            fresh.close()
    finally:
        a.close()
        b.close()


def test_a_bad_settle_setting_names_the_variable(monkeypatch):
    require_adapter()
    from pointflow.render.base import RenderError
    from pointflow.render.wgpu_tier import WgpuRenderer
    monkeypatch.setenv(compact.ENV_COMPACT, "1")
    monkeypatch.setenv(compact.ENV_SETTLE, "soon")
    with pytest.raises(RenderError, match="POINTFLOW_WGPU_COMPACT_SETTLE must be a whole number"):
        WgpuRenderer(render_cfg(size=[64, 48], raster="compute"), 1_000, ["intensity"])
