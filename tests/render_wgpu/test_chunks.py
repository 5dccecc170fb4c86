"""Issue 31 item 7: a ring larger than one storage binding is drawn whole.

The tier keeps the ring's slots in chunks that each fit one binding and walks them in
segments (pointflow/render/wgpu_tier/chunks.py). Before, it drew only the first
``binding / 12`` slots (11,184,810 on lavapipe's 128 MiB) and said so once in the log."""
from __future__ import annotations

import numpy as np
import pytest

from pointflow.config import EdlConfig
from pointflow.render.camera import Camera
from pointflow.render.wgpu_tier import chunks

from .helpers import cfg, frame


# ----------------------------------------------------------------------------- the walk
@pytest.mark.parametrize("cap,clen,head,size,drawn", [
    (10_000, 2_560, 0, 10_000, 10_000), (10_000, 2_560, 3_000, 10_000, 10_000),
    (10_000, 2_560, 9_999, 7_000, 10_000), (10_000, 2_560, 4_000, 1_500, 10_000),
    (10_000, 2_560, 6_000, 10_000, 7_000), (5_120, 2_560, 2_560, 5_120, 5_120)])
def test_segments_walk_every_logical_index_once_in_order(cap, clen, head, size, drawn):
    table = chunks.chunks(drawn, clen)  # the tier's slots (a frame's ring may be larger)
    assert sum(n for _, n in table) == drawn and all(n <= clen for _, n in table)
    segs = chunks.segments(head, size, cap, drawn, table)
    logical, slots = [], []
    windows: dict[int, list[tuple[int, int]]] = {}
    for i, s in enumerate(segs):
        a, n = table[s.chunk]
        assert s.index == i and s.slot_base == a and s.capacity == n and s.head + s.size <= n
        logical.extend(range(s.logical_base, s.logical_base + s.size))
        slots.extend(range(a + s.head, a + s.head + s.size))
        windows.setdefault(s.chunk, []).append((s.out_off, s.out_off + s.size))
    want = [(head + i) % cap for i in range(size)]
    keep = [i for i, sl in enumerate(want) if sl < drawn]
    assert logical == keep and slots == [want[i] for i in keep]
    for c, w in windows.items():  # output windows of one chunk: aligned, disjoint, within n + pad
        w.sort()
        assert all(o % chunks.OUT_ALIGN == 0 for o, _ in w)
        assert all(b0 <= a1 for (_, b0), (a1, _) in zip(w, w[1:]))
        assert w[-1][1] <= table[c][1] + chunks.OUT_ALIGN
    assert len(segs) <= len(table) + 1


def test_one_chunk_is_one_wrapping_segment():
    segs = chunks.segments(700, 1000, 1000, 1000, chunks.chunks(1000, 4096))
    assert [(s.head, s.size, s.capacity, s.logical_base) for s in segs] == [(700, 1000, 1000, 0)]


# ----------------------------------------------------------------------------- the image
def _scene(n, cap, head, seed=4):
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-3, 3, size=(n, 3))
    # equal depths across chunks: a red point early (logical 10) and a blue one late at the
    # same place; the lower logical index must win in every method and chunking
    pts[n - 10] = pts[10] = [0.0, -6.0, 1.0]  # on the view axis, in front of every other point
    inten = rng.uniform(0, 1, n).astype(np.float32)
    inten[10], inten[n - 10] = 0.0, 1.0
    imp = rng.uniform(0, 1, n).astype(np.float32)
    t = np.linspace(0, 1000, n)
    return pts, inten, imp, t


@pytest.mark.parametrize("extra", [{}, {"importance_sampling": True, "lod_stride": 2},
                                   {"time_window_ms": 600.0, "point_shape": "round", "point_size": 3.0,
                                    "edl": EdlConfig(enabled=True)}],
                         ids=["plain", "sampled", "window-round-edl"])
def test_a_ring_in_many_chunks_draws_what_one_binding_draws(make_renderer, raster, extra):
    """A 40k ring whose head wraps, split into 7-11 chunks by a 64 KiB binding limit: the same
    image, counts, survivors and picks as one binding, with and without a budget (the budget's
    fraction and hard cap run over all segments in logical order)."""
    n, cap, head = 38_000, 40_000, 27_000
    pts, inten, imp, t = _scene(n, cap, head)
    cam = Camera(eye=[0.0, -12.0, 2.0], target=[0.0, 0.0, 0.0], near=1.0, far=100.0)
    c = cfg(color_by="intensity", color_range="auto", **extra)
    one = make_renderer(c, cap, ["intensity"])
    many = make_renderer(c, cap, ["intensity"], max_binding=64 * 1024)
    assert one.info()["chunks"] == 1 and many.info()["chunks"] >= 7
    for budget in (None, 9000, 20):
        f = frame(pts, capacity=cap, head=head, channels={"intensity": inten}, importance=imp, t_ms=t,
                  now_ms=1000.0, budget=budget, seed=3)
        sa, sb = one.render(f, cam), many.render(f, cam)
        ia, ib = one.read_image(), many.read_image()
        assert (ia != ia[0, 0]).any(-1).mean() > (0.01 if budget is None else 0.0)
        bad = (ia != ib).any(-1)
        assert not bad.any(), f"budget {budget}: {int(bad.sum())} pixels differ"
        assert sa.drawn == sb.drawn and (budget is None or sa.drawn <= budget)
        assert sa.extra["occupied"] == sb.extra["occupied"] == n
        assert np.array_equal(one.debug_survivors(), many.debug_survivors())
        for x, y in ((160, 120), (100, 80), (200, 150)):
            assert one.pick(x, y) == many.pick(x, y)


def test_the_lower_logical_index_wins_a_tie_across_chunks(make_renderer):
    n, cap, head = 38_000, 40_000, 27_000
    pts, inten, imp, t = _scene(n, cap, head)
    cam = Camera(eye=[0.0, -12.0, 2.0], target=[0.0, 0.0, 0.0], near=1.0, far=100.0)
    r = make_renderer(cfg(color_by="intensity", color_range=[0.0, 1.0], colormap="grayscale", point_size=9.0),
                      cap, ["intensity"], max_binding=64 * 1024)
    f = frame(pts, capacity=cap, head=head, channels={"intensity": inten})
    r.render(f, cam)
    img = r.read_image()
    # logical 10 (intensity 0: black) in the first segment beats logical n-10 (white) in the last
    assert tuple(img[120, 160, :3]) == (0, 0, 0)
    assert r.pick(160, 120) == (head + 10) % cap


def test_a_ring_above_the_storage_binding_limit_is_drawn_whole(make_renderer, raster):
    """A ring of more slots than one 128 MiB binding holds (positions 12 B each: 11,184,810
    points) on the real device limit: points placed in the very last slots, and the newest
    logical index, show in the frame (before, they were silently not drawn)."""
    probe = make_renderer(cfg(), 16)
    limit = int(probe.info()["limits"]["max-storage-buffer-binding-size"])
    over = limit // 12 + 50_000
    if over > 40_000_000:
        pytest.skip(f"this adapter binds {limit} bytes per storage buffer: a ring above it is too big to test")
    cap = (over + 4095) // 4096 * 4096
    pos = np.zeros((cap, 3), np.float32)
    pos[:, 1] = -50.0  # behind the camera: culled
    # three points at known places: the last slot, the one before, and the newest (wrapped)
    head = cap - 1_000
    places = {cap - 1: (-2.0, 0.0, 0.0), cap - 2: (2.0, 0.0, 0.0), (head - 1) % cap: (0.0, 0.0, 1.5)}
    for slot, p in places.items():
        pos[slot] = p
    from pointflow.render.base import FrameInput
    f = FrameInput(positions=pos, importance=np.zeros(cap, np.float32), t_ingest_ms=np.zeros(cap),
                   channels={}, head=head, size=cap, capacity=cap, origin=np.zeros(3), now_ms=0.0)
    del pos
    cam = Camera(eye=[0.0, -10.0, 0.0], target=[0.0, 0.0, 0.0], near=1.0, far=100.0)
    r = make_renderer(cfg(size=[160, 120], point_size=5.0, color=[1.0, 1.0, 1.0]), cap)
    assert r.info()["chunks"] >= 2 and r.info()["render_capacity"] == cap
    st = r.render(f, cam)
    img = r.read_image()
    assert st.drawn == 3 and st.extra["occupied"] == cap
    xy = cam.view_proj(160, 120, np.zeros(3))
    for slot, p in places.items():
        c = xy @ np.array([*p, 1.0])
        x, y = int((c[0] / c[3] * 0.5 + 0.5) * 160), int((0.5 - c[1] / c[3] * 0.5) * 120)
        assert tuple(img[y, x, :3]) == (255, 255, 255), f"slot {slot} not drawn"
        assert r.pick(x, y) == slot
