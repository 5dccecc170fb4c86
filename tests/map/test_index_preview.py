"""The map drawn while its index is built (issue 37): the build's first pass hands the map stage
an evenly spread share of each chunk it reads, so a cold file is drawn before its index is
done. Checked at the build itself (deterministic: inside the callback the index does not exist
yet) and in real processes (the render stage draws the preview, then the index's nodes)."""
from __future__ import annotations

import os
import time

import numpy as np
from PIL import Image

from pointflow import Pipeline
from pointflow.config import RenderConfig
from pointflow.map import open_map
from pointflow.map.build import index_dir
from pointflow.map.inputs import CHUNK_POINTS, FIRST_CHUNK
from pointflow.render.base import FrameInput
from pointflow.render.camera import Camera
from pointflow.render.cpu import CpuRenderer

from .mapfiles import laspy_points, write_las


def test_preview_points_draw_before_the_index_exists(tmp_path):
    n = FIRST_CHUNK * 3 + 1000  # several chunks: the first (small) one comes at once
    las = write_las(str(tmp_path / "big.laz"), n, seed=3)
    truth = laspy_points(las)["positions"]
    cache = str(tmp_path / "cache")
    seen, pngs = [], []

    def preview(file_index: int, data: dict) -> None:
        assert file_index == 0
        assert not os.path.exists(os.path.join(index_dir(las, cache), "meta.json")), "the index is not built yet"
        seen.append(data["positions"])
        if len(pngs) == 0:  # draw the first share, as the render stage would, to a PNG
            pos = data["positions"]
            origin = pos.mean(axis=0)
            k = pos.shape[0]
            frame = FrameInput(positions=(pos - origin).astype(np.float32), importance=np.ones(k, np.float32),
                               t_ingest_ms=np.zeros(k), channels={}, head=0, size=k, capacity=k, origin=origin,
                               now_ms=0.0)
            r = CpuRenderer(RenderConfig(size=(160, 120), point_size=2.0), k, [])
            r.render(frame, Camera.fit(truth.min(axis=0), truth.max(axis=0), aspect=160 / 120))
            path = str(tmp_path / "preview.png")
            Image.fromarray(r.read_image()).save(path)
            pngs.append(path)

    with open_map(las, cache_dir=cache, progress=False, preview=preview, preview_points=20_000) as m:
        assert m.point_count == n
    assert len(seen) == 1 + -(-(n - FIRST_CHUNK) // CHUNK_POINTS), "one share per chunk read"
    assert seen[0].shape[0] <= FIRST_CHUNK // (n // 20_000) + 1, "the first, small chunk's share came first"
    got = np.concatenate(seen)
    assert 15_000 <= got.shape[0] <= 20_004, "about preview_points in all, spread over the chunks"
    # every preview point is one of the file's points, exactly (laspy's own scaling)
    key = lambda p: set(map(tuple, np.round(p, 6)))  # noqa: E731
    assert key(got) <= key(truth)
    assert got[:, 0].max() - got[:, 0].min() > 0.9 * (truth[:, 0].max() - truth[:, 0].min()), "spread out"
    img = np.asarray(Image.open(pngs[0]))[..., :3]
    assert (img != img[0, 0]).any(axis=-1).mean() > 0.05, "the first chunk's share draws a picture"


def test_a_cold_map_is_drawn_from_its_preview_then_its_index(tmp_path):
    """In real processes: the render stage takes a preview version (points, no nodes) before the
    map is open, then the index's nodes replace it; the live line says ``map: indexing N%``."""
    from pointflow.profiling.report import live_summary

    n = FIRST_CHUNK * 4
    las = write_las(str(tmp_path / "cold.laz"), n, seed=4)
    cfg = {"source": {"transport": "synthetic", "options": {"scan_hz": 10, "points_per_scan": 2000}},
           "ring": {"max_points": 20_000},
           "render": {"backend": "cpu", "size": [160, 120], "output": {"every_n_frames": 100000}},
           "map": {"path": las, "point_budget": 600_000, "cache_dir": str(tmp_path / "cache")}}
    lines = []
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path / "out")) as pipe:
        def watch():
            st = pipe.stats()
            lines.append(live_summary(st))
            return st["stages"].get("render", {}).get("map_points", 0) >= n
        pipe.wait(240, until=watch)
        ren = pipe.stats()["stages"]["render"]
        assert ren["map_previews_taken"] >= 1, "a preview version reached the render stage"
        assert ren["map_preview"] is False and ren["map_points"] == n, "then the index's nodes, all of the file"
        img = np.asarray(Image.open(pipe.save_frame(str(tmp_path / "map.png"))))[..., :3]
        assert (img != img[0, 0]).any(axis=-1).mean() > 0.05
    shown = [ln for ln in lines if "map: indexing" in ln or "map=" in ln]
    assert shown, lines[-3:]


def test_a_preview_is_drawn_then_dropped_when_the_map_fails(tmp_path):
    """The map stage's preview side against the render stage's map layer, over real sockets: the
    offered points arrive as a preview version (the header's bounds with them); a map that then
    fails to open clears them (an empty full version), and the bounds go with it."""
    import types

    import zmq

    from pointflow.render import mapregion as mr
    from pointflow.map.preview import Preview
    from pointflow.render.maplayer import MapLayer

    from .test_one_picture_layer import _ctx, _ring_frame, _scene

    cfg, ctx = _ctx(str(tmp_path), 1000)
    layer = MapLayer(cfg, ctx, 100)
    push = ctx.zmq.socket(zmq.PUSH)
    push.setsockopt(zmq.LINGER, 0)
    push.connect(ctx.endpoints.map)
    stage = types.SimpleNamespace(info=types.SimpleNamespace(run_dir=str(tmp_path)),
                                  counters=types.SimpleNamespace(extra={}))
    live, li, pts, _ = _scene(10, 300)
    bounds = (pts.min(axis=0), pts.max(axis=0))
    pv = Preview(stage, 1000, lambda avail: [mr.channel_spec(c) for c in avail], bounds, ["/data/tile.laz"], push)
    try:
        pv.offer(0, {"positions": pts, "intensity": np.arange(300, dtype=np.float32)})
        pv.step()

        def until(cond):
            end = time.monotonic() + 30
            while time.monotonic() < end and not cond():
                layer.poll()
                time.sleep(0.01)
            assert cond()
        until(lambda: layer.points == 300)
        assert layer.preview and layer.map_box is not None
        f = layer.compose(_ring_frame(live, li, 100))
        assert np.isfinite(f.positions[100:400]).all(), "the preview's points are in the frame"
        push.send(mr.encode({"type": "bounds", "bounds": None}))  # as the stage does on the error
        pv.clear()
        until(lambda: layer.points == 0)
        assert layer.map_box is None
        f = layer.compose(_ring_frame(live, li, 100))
        assert np.isnan(f.positions[100:]).all(), "nothing of the failed map is drawn"
    finally:
        push.close(0)
        layer.close()
        if pv.region is not None:
            pv.region.close()
            pv.region.unlink()


def test_a_build_stopped_midway_leaves_no_folder(tmp_path):
    """The map stage stopped while its index is built (Ctrl-C) removes the half-built folder
    on its way out (build.remove_unfinished; a 272 MB spill folder was left behind until
    the same file was opened again). The build is held inside its preview callback here."""
    import glob
    import threading

    from pointflow.map import build

    las = write_las(str(tmp_path / "big.laz"), FIRST_CHUNK * 2 + 100, seed=5)
    cache = str(tmp_path / "cache")
    inside, release, errors = threading.Event(), threading.Event(), []

    def preview(file_index: int, data: dict) -> None:
        inside.set()
        release.wait(60)

    def run() -> None:
        try:
            open_map(las, cache_dir=cache, progress=False, preview=preview, preview_points=1000)
        except BaseException as exc:  # noqa: BLE001 - its folder was taken away mid-build
            errors.append(exc)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    assert inside.wait(60)
    half = glob.glob(os.path.join(cache, "**", "*.tmp-*"), recursive=True)
    assert len(half) == 1 and os.path.isdir(half[0]), half
    assert build.remove_unfinished() == half
    assert not os.path.exists(half[0])
    release.set()
    t.join(60)
    assert not glob.glob(os.path.join(cache, "**", "*.tmp-*"), recursive=True)
    assert build.remove_unfinished() == []
