"""The compiled cpu raster on every core (issue 41): the binned split (records sorted by
screen band in one pass over the points, each band keyed and resolved by one thread) draws
the same bytes as the other splits and the float64 reference, whatever the thread count,
across the ring's wrap, with records that overflow their first guess, boxes over many bands,
and a ring rewritten between frames."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from conftest import draw
from scenes import SCENES, make_frame, render_cfg, terrain, terrain_camera

from pointflow.config import EdlConfig
from pointflow.render.base import FrameInput
from pointflow.render.camera import Camera
from pointflow.render.cpu import CpuRenderer
import pointflow.render.cpu_compute as cc
from pointflow.render.cpu_compute import CpuComputeRenderer

numba = pytest.importorskip("numba")
HERE = os.path.dirname(__file__)


@pytest.fixture(autouse=True)
def _threads():
    n = numba.get_num_threads()
    yield
    numba.set_num_threads(n)


def renderer(monkeypatch, split, cfg, frame):
    monkeypatch.setenv("POINTFLOW_CPU_RASTER_SPLIT", split)
    monkeypatch.setenv("POINTFLOW_CPU_RASTER_ADAPTIVE", "0")
    return CpuComputeRenderer(cfg, frame.capacity, list(frame.channels))


def test_byte_identical_at_one_to_four_threads_in_every_split():
    """In a fresh interpreter with four numba threads (more than this machine may have:
    the image cannot depend on it): every split at 1, 2, 3 and 4 threads, four scenes (EDL on
    the world-size one), the same image bytes and the same winners everywhere."""
    script = textwrap.dedent(f"""
        import hashlib, json, sys
        sys.path.insert(0, {HERE!r})
        import numba
        from scenes import SCENES, render_cfg
        from pointflow.config import EdlConfig
        import os
        from pointflow.render.cpu_compute import CpuComputeRenderer
        out = {{}}
        for name in ("terrain", "sphere", "georeferenced", "world_rgb_filters"):
            frame, cam, kw = SCENES[name]()
            for split in ("auto", "bins", "points", "bands"):
                os.environ["POINTFLOW_CPU_RASTER_SPLIT"] = split
                os.environ["POINTFLOW_CPU_RASTER_ADAPTIVE"] = "0"
                cfg = render_cfg(size=[320, 240], edl=EdlConfig(enabled=name == "world_rgb_filters"), **kw)
                for t in (1, 2, 3, 4):
                    numba.set_num_threads(t)
                    r = CpuComputeRenderer(cfg, frame.capacity, list(frame.channels))
                    frame.dirty = None
                    st = r.render(frame, cam)
                    assert st.extra["threads"] == t
                    h = hashlib.sha256(r.read_image().tobytes() + r.winners().tobytes()).hexdigest()
                    out[f"{{name}}/{{split}}/{{t}}"] = [h, st.drawn, st.extra["split"]]
        print(json.dumps(out))
        """)
    env = {**os.environ, "NUMBA_NUM_THREADS": "4"}
    p = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=900)
    assert p.returncode == 0, p.stderr[-3000:]
    got = json.loads(p.stdout.strip().splitlines()[-1])
    for name in ("terrain", "sphere", "georeferenced", "world_rgb_filters"):
        rows = {k: v for k, v in got.items() if k.startswith(name + "/")}
        assert len(rows) == 16
        assert len({v[0] for v in rows.values()}) == 1, f"{name}: images differ: {rows}"
        assert len({v[1] for v in rows.values()}) == 1
        assert {v[2] for k, v in rows.items() if "/bins/" in k} == {"bins"}


@pytest.mark.parametrize("threads", [1, 2])
def test_batches_that_straddle_the_wrap_culled_or_not(monkeypatch, threads):
    """Batches of 256 slots over a ring whose occupied range wraps past the end, the head in
    the middle of a batch (that batch is cut in two chunks and never culled whole), the points
    sorted by x so that a view of one end culls whole batches at the other: the binned image,
    culling on and off, equals the reference and the points split, byte for byte."""
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    monkeypatch.setattr(cc, "BIN_CHUNK", 256)
    w = terrain(5_000, seed=9)
    w = w[np.argsort(w[:, 0])]
    f = make_frame(w, capacity=5_300, head=5_300 - 1_000, intensity=np.linspace(0, 1, len(w), dtype=np.float32))
    assert f.head + f.size > f.capacity and f.head % 256 != 0  # wraps; the head inside a batch
    cfg = render_cfg(size=[320, 240], point_size=3)
    cam = Camera(eye=[-35, -5, 40], target=[-35, 0, 0], near=1, far=200, fov_deg=40)  # looks down at the x < 0 end
    a, sa = draw(CpuRenderer(cfg, f.capacity, list(f.channels)), f, cam)
    imgs = {}
    for cull in ("1", "0"):
        monkeypatch.setenv("POINTFLOW_CPU_RASTER_CULL", cull)
        bins = renderer(monkeypatch, "bins", cfg, f)
        imgs[cull], sb = draw(bins, f, cam)
        assert sb.drawn == sa.drawn and sb.extra["split"] == "bins"
        assert (sb.extra["culled_points"] > 1_000) == (cull == "1")
    p, _ = draw(renderer(monkeypatch, "points", cfg, f), f, cam)
    assert (a != a[0, 0]).any(axis=-1).mean() > 0.05, "the view must show points"
    assert np.array_equal(a, imgs["1"]) and np.array_equal(imgs["1"], imgs["0"]) and np.array_equal(imgs["1"], p)


def test_culled_batches_keep_the_counts_and_the_automatic_colour_range(monkeypatch):
    """A culled batch touches no point, yet the frame's non-finite count and the automatic
    colour range (over every occupied point, seen or not) are those of the whole ring."""
    monkeypatch.setattr(cc, "BIN_CHUNK", 512)
    w = terrain(8_192, seed=13)
    w = w[np.argsort(w[:, 0])]
    w[7_000] = np.nan  # in a batch the view culls
    z = w[:, 2].copy()
    f = make_frame(w)
    cfg = render_cfg(size=[200, 150], point_size=2, color_by="z")
    cam = Camera(eye=[-35, -5, 40], target=[-35, 0, 0], near=1, far=200, fov_deg=40)  # looks down at the x < 0 end
    ref, sa = draw(CpuRenderer(cfg, f.capacity, list(f.channels)), f, cam)
    got, sb = draw(renderer(monkeypatch, "bins", cfg, f), f, cam)
    assert sb.extra["culled_points"] > 4_000
    assert sb.extra["removed_nonfinite"] == sa.extra["removed_nonfinite"] == 1
    assert np.nanmax(z) > np.nanmax(z[:4_000])  # the range's top lies in the culled batches
    assert np.array_equal(got, ref)


def test_records_that_overflow_the_first_guess_grow_and_draw_the_same(monkeypatch):
    """Round 9 px points cross band edges often: with a first guess of 0.1 record per point
    every chunk overflows, the pass runs again with room for what it needed, and the image is
    the points split's."""
    monkeypatch.setattr(cc, "RECORDS_PER_POINT", 0.1)
    w = terrain(6_000, seed=10)
    f = make_frame(w, intensity=np.linspace(0, 1, len(w), dtype=np.float32))
    cfg = render_cfg(size=[320, 240], point_size=9, point_shape="round")
    r = renderer(monkeypatch, "bins", cfg, f)
    b, _ = draw(r, f, terrain_camera())
    assert r._records_per_point > 0.1 and r._bins.RC >= int(r._bins.off[0, -1])  # grown to what was needed
    p, _ = draw(renderer(monkeypatch, "points", cfg, f), f, terrain_camera())
    assert np.array_equal(b, p)
    assert np.array_equal(b, draw(CpuRenderer(cfg, f.capacity, list(f.channels)), f, terrain_camera())[0])


@pytest.mark.parametrize("shape", ["square", "round"])
def test_boxes_over_many_bands_share_one_bucket(monkeypatch, shape):
    """Points of 100 px cover 7+ bands: each goes once into the bucket every band reads, and
    the image and the picks equal the points split's."""
    rng = np.random.default_rng(11)
    w = rng.uniform(-20, 20, (300, 3))
    f = make_frame(w, intensity=rng.random(300).astype(np.float32))
    cfg = render_cfg(size=[320, 240], point_size=100, point_shape=shape)
    cam = Camera(eye=[0, -60, 30], target=[0, 0, 0], near=1, far=200)
    r = renderer(monkeypatch, "bins", cfg, f)
    b, _ = draw(r, f, cam)
    bn = r._bins
    assert (bn.off[:, bn.NB + 1] - bn.off[:, bn.NB]).sum() > 0  # the shared bucket is used
    q = renderer(monkeypatch, "points", cfg, f)
    p, _ = draw(q, f, cam)
    assert np.array_equal(b, p)
    assert np.array_equal(r.winners(), q.winners())
    assert np.array_equal(r.winners(30, 70, 10, 300), q.winners(30, 70, 10, 300))  # a block over bands


@pytest.mark.parametrize("split", ["bins", "auto"])
def test_a_ring_rewritten_between_frames(monkeypatch, split):
    """A ring rewritten frame after frame (partly, wrapping, then wholly): every frame equals
    the reference, and picks read the frame just drawn (the records, not the own copy)."""
    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    cap = 9_000
    rng = np.random.default_rng(12)
    pos = np.zeros((cap, 3), np.float32)
    inten = np.zeros(cap, np.float32)
    cfg = render_cfg(size=[200, 150], point_size=2)
    cam = Camera(eye=[0, -30, 20], target=[0, 0, 0], near=1, far=100)
    f0 = FrameInput(positions=pos, importance=np.zeros(cap, np.float32), t_ingest_ms=np.zeros(cap),
                    channels={"intensity": inten}, head=0, size=0, capacity=cap, origin=np.zeros(3), now_ms=0.0)
    got = renderer(monkeypatch, split, cfg, f0)
    ref = CpuRenderer(cfg, cap, ["intensity"])
    write, size = 0, 0
    for k, n in enumerate((4_000, 3_000, 3_500, 2_000, cap)):
        slots = (write + np.arange(n)) % cap
        pos[slots] = rng.uniform(-10, 10, (n, 3))
        inten[slots] = rng.random(n)
        dirty = [(write, (write + n) % cap)] if n < cap else [(0, cap)]
        write = (write + n) % cap
        size = min(size + n, cap)
        f = FrameInput(positions=pos, importance=np.zeros(cap, np.float32), t_ingest_ms=np.zeros(cap),
                       channels={"intensity": inten}, head=(write - size) % cap, size=size, capacity=cap,
                       origin=np.zeros(3), now_ms=0.0, dirty=None if k == 0 else dirty)
        img, st = draw(got, f, cam)
        want, _ = draw(ref, f, cam)
        assert np.array_equal(img, want), f"frame {k}"
        assert st.extra["split"] == (split if split != "auto" else got._rule(st.extra["threads"]))
        before, kept = got.winners(), pos.copy()
        pos[:] = rng.uniform(-10, 10, (cap, 3))  # the ring moves on, unannounced, before the next frame
        assert np.array_equal(got.winners(), before)
        pos[:] = kept
        hit = np.argwhere(before >= 0)[0]
        assert got.pick(float(hit[1]) + 0.5, float(hit[0]) + 0.5) is not None


def test_auto_times_both_splits_at_both_thread_counts_and_keeps_the_image(monkeypatch):
    """``auto``: the first frames draw with bins and points at every thread and at one, the
    fastest then draws, and the others are re-tried in rotation; one image throughout."""
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one core: nothing to choose")
    numba.set_num_threads(2)
    frame, cam, kw = SCENES["terrain"]()
    monkeypatch.delenv("POINTFLOW_CPU_RASTER_ADAPTIVE", raising=False)
    r = renderer(monkeypatch, "auto", render_cfg(size=[320, 240], **kw), frame)
    monkeypatch.delenv("POINTFLOW_CPU_RASTER_ADAPTIVE", raising=False)
    r._adaptive = True
    used, imgs = [], set()
    for i in range(4 * cc.TUNE_FRAMES):
        frame.dirty = None if i == 0 else []
        st = r.render(frame, cam)
        used.append((st.extra["split"], st.extra["threads"]))
        imgs.add(r.read_image().tobytes())
    first = [("bins", 2), ("points", 2), ("bins", 1), ("points", 1)]
    assert used == [c for c in first for _ in range(cc.TUNE_FRAMES)] and len(imgs) == 1
    r._tune = {c: [float(k + 1)] * cc.TUNE_FRAMES for k, c in enumerate(first)}  # bins at 2 threads fastest
    picks = [r._pick() for _ in range(3 * cc.RETRY_EVERY)]
    assert picks.count(("bins", 2)) == 3 * cc.RETRY_EVERY - 3
    assert sorted(p for p in picks if p != ("bins", 2)) == sorted(first[1:])  # each other one re-tried


def _sparse():
    """A few hundred points: most tiles a box reaches from the next tile are not marked."""
    w = terrain(600, seed=5)
    return make_frame(w, intensity=((w[:, 2] + 3) / 14).astype(np.float32)), terrain_camera(), dict(point_size=2)


@pytest.mark.parametrize("name,edl,fixed", [("terrain", False, False), ("terrain", True, True),
                                            ("sparse", False, True), ("world_rgb_filters", True, False)])
def test_tiles_written_last_frame_are_cleared_whatever_comes_next(monkeypatch, name, edl, fixed):
    """The points split clears and resolves only the tiles its buffers marked: one renderer
    drawing a camera that zooms in, pans away and back, at 2, 1 and 2 threads, after a frame of
    the bins and of the bands split, on a size the tiles do not divide, draws every frame as a
    fresh renderer does (image and winners), EDL on or off; a fixed colour range takes the
    lean loop's 2x2 path (a box marked by its first pixel's tile only), an automatic one and
    round world-size points the general one."""
    frame, cam, kw = _sparse() if name == "sparse" else SCENES[name]()
    if fixed:
        kw = dict(kw, color_range=[-3.0, 11.0])
    cfg = render_cfg(size=[331, 243], edl=EdlConfig(enabled=edl), **kw)
    got = renderer(monkeypatch, "points", cfg, frame)
    eye, target = np.asarray(cam.eye, float), np.asarray(cam.target, float)
    cams = [cam, Camera(eye=list(target + (eye - target) * 0.4), target=list(target), near=cam.near, far=cam.far),
            Camera(eye=list(eye + [40.0, 0, 0]), target=list(target + [40.0, 0, 0]), near=cam.near, far=cam.far),
            cam, Camera(eye=list(target + (eye - target) * 0.6), target=list(target + [3.0, 2.0, 0]),
                        near=cam.near, far=cam.far)]
    most = max(2, min(4, numba.config.NUMBA_NUM_THREADS))
    plan = [("points", most), ("points", 1), ("bins", most), ("points", most), ("bands", most), ("points", 1),
            ("points", most)]
    for k, (split, t) in enumerate(plan):
        c = cams[k % len(cams)]
        numba.set_num_threads(min(t, numba.config.NUMBA_NUM_THREADS))
        got.split_mode, got.bands = split, split == "bands"
        frame.dirty = None if k == 0 else []
        img, st = draw(got, frame, c)
        fresh = renderer(monkeypatch, split, cfg, frame)
        frame.dirty = None
        want, _ = draw(fresh, frame, c)
        assert np.array_equal(img, want), f"frame {k} ({split}, {t} threads)"
        assert np.array_equal(got.winners(), fresh.winners()), f"frame {k}"
        assert st.drawn > 0


@pytest.mark.parametrize("point_size", [2, 37])
def test_boxes_that_reach_into_the_next_tile_are_drawn_and_cleared(monkeypatch, point_size):
    """Points alone in their tile whose box reaches one pixel into the tile right of, below,
    or below-right of it (a 2x2 box is marked by its first pixel's tile only; a 37x37 one by every
    tile it covers): drawn as the bands split draws them (one buffer, read whole), then cleared
    when the ring moves them."""
    from pointflow.render import cpu_kernels as ck
    W, H = 8 * (1 << ck.TILE_XS) + 5, 6 * (1 << ck.TILE_YS) + 3
    cam = Camera(eye=[0, -20, 5], target=[0, 0, 0], near=1, far=100)
    inv = np.linalg.inv(cam.view_proj(W, H, np.zeros(3)))
    tx, ty = 1 << ck.TILE_XS, 1 << ck.TILE_YS
    px = []
    for j in range(0, 6, 2):
        for i in range(0, 8, 2):
            kind = (i // 2 + j // 2) % 3  # right, below, below-right
            x = i * tx + (tx - 0.1 if kind != 1 else 7.5)
            y = j * ty + (ty - 0.1 if kind != 0 else 5.5)
            px.append((x, y))
    px = np.array(px)
    ndc = np.c_[px[:, 0] / W * 2 - 1, 1 - px[:, 1] / H * 2, np.full(len(px), 0.9), np.ones(len(px))]
    world = ndc @ inv.T
    world = (world[:, :3] / world[:, 3:]).astype(np.float32)
    cap = len(world)
    pos = world.copy()
    inten = np.linspace(0, 1, cap, dtype=np.float32)
    f = FrameInput(positions=pos, importance=np.zeros(cap, np.float32), t_ingest_ms=np.zeros(cap),
                   channels={"intensity": inten}, head=0, size=cap, capacity=cap, origin=np.zeros(3), now_ms=0.0)
    cfg = render_cfg(size=[W, H], point_size=point_size, color_range=[0.0, 1.0])
    numba.set_num_threads(1)
    got = renderer(monkeypatch, "points", cfg, f)
    ref = renderer(monkeypatch, "bands", cfg, f)
    for k in range(3):
        if k == 1:
            pos[:] = world + np.float32(0.35)  # every point moves: last frame's tiles must be cleared
        if k == 2:
            pos[:] = world
        f.dirty = None if k == 0 else [(0, cap)]
        img, st = draw(got, f, cam)
        want, _ = draw(ref, f, cam)
        assert st.drawn == cap
        assert np.array_equal(img, want), f"frame {k}"
