"""What the wgpu tier keeps from one frame to the next so that a still camera costs little on
the CPU (issue 41, item 4): the view's part of the Params record (``frame_params.ViewCache``),
the plane test per batch (``BatchBounds``), the compute method's own parameters. Each is
checked against a fresh renderer: a camera moved in place, a colour or background changed
in the config, a pick between frames, and a batch rewritten into view under a still camera."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from conftest import draw
from gpu_util import require_adapter
from scenes import make_frame, render_cfg, terrain

import pointflow.render.batches as batches
from pointflow.render.camera import Camera

METHODS = ["compute", "quads"]
#: the two ends of a terrain sorted by x, seen from above: each view culls the other end
WEST = dict(eye=[-35.0, -5.0, 40.0], target=[-35.0, 0.0, 0.0])
EAST = dict(eye=[35.0, -5.0, 40.0], target=[35.0, 0.0, 0.0])


@pytest.fixture(autouse=True)
def _small_batches(monkeypatch):
    monkeypatch.setattr(batches, "BATCH_SLOTS", 256)


def _renderer(cfg, cap):
    require_adapter()
    from pointflow.render.wgpu_tier import WgpuRenderer
    return WgpuRenderer(cfg, cap, ["intensity"])


def _scene():
    w = terrain(6_000, seed=5)
    w = w[np.argsort(w[:, 0])]
    return make_frame(w, intensity=np.linspace(0, 1, len(w), dtype=np.float32))


def _fresh(cfg, f, cam):
    r = _renderer(cfg, f.capacity)
    try:
        return draw(r, f, cam)
    finally:
        r.close()


@pytest.mark.parametrize("method", METHODS)
def test_a_camera_moved_in_place_is_seen(method):
    """The same Camera object, its arrays changed in place between frames: the second frame
    is the fresh renderer's image of the new view, culling the other end."""
    cfg = render_cfg(size=[240, 180], point_size=3, color_by="intensity", raster=method)
    f = _scene()
    cam = Camera(**WEST, near=1, far=200, fov_deg=40)
    r = _renderer(cfg, f.capacity)
    try:
        west, s_west = draw(r, f, cam)
        cam.eye[:] = EAST["eye"]
        cam.target[:] = EAST["target"]
        east, s_east = draw(r, f, cam)
        cam.fov_deg = 60.0  # a field of view changed on the same object
        wide, _ = draw(r, f, cam)
        cam.eye, cam.target, cam.fov_deg = list(WEST["eye"]), list(WEST["target"]), 40.0  # lists, not arrays
        back, _ = draw(r, f, cam)
    finally:
        r.close()
    assert np.array_equal(back, west)
    ref_east, s_ref = _fresh(cfg, f, Camera(**EAST, near=1, far=200, fov_deg=40))
    ref_wide, _ = _fresh(cfg, f, Camera(**EAST, near=1, far=200, fov_deg=60))
    assert not np.array_equal(west, east), "the views must differ"
    assert np.array_equal(east, ref_east)
    assert np.array_equal(wide, ref_wide) and not np.array_equal(wide, east)
    assert s_east.drawn == s_ref.drawn
    assert s_west.extra["culled_points"] > 0 and s_east.extra["culled_points"] > 0
    assert s_east.extra["culled_points"] == s_ref.extra["culled_points"]


@pytest.mark.parametrize("method", METHODS)
def test_colour_and_background_changed_in_the_config_are_drawn(method):
    """``cfg.color`` and ``cfg.background`` changed on the renderer's own config between
    frames: drawn as a fresh renderer with those values draws them."""
    cfg = render_cfg(size=[200, 150], point_size=3, color_by="none", color=[0.2, 0.9, 0.3],
                     background=[0.0, 0.0, 0.0], raster=method)
    f = _scene()
    cam = Camera(**WEST, near=1, far=200, fov_deg=40)
    r = _renderer(cfg, f.capacity)
    try:
        first, _ = draw(r, f, cam)
        r.cfg.color = [0.9, 0.1, 0.1]
        r.cfg.background = [0.1, 0.1, 0.4]
        second, _ = draw(r, f, cam)
    finally:
        r.close()
    ref, _ = _fresh(dataclasses.replace(cfg, color=[0.9, 0.1, 0.1], background=[0.1, 0.1, 0.4]), f, cam)
    assert not np.array_equal(first, second)
    assert np.array_equal(second, ref)


@pytest.mark.parametrize("method", METHODS)
def test_a_pick_between_frames_changes_no_frame(method):
    """A pick writes its own parameters (the compute method's block); the next frame of the
    same view is the frame before it, byte for byte."""
    cfg = render_cfg(size=[200, 150], point_size=3, color_by="intensity", raster=method)
    f = _scene()
    cam = Camera(**WEST, near=1, far=200, fov_deg=40)
    r, fresh = _renderer(cfg, f.capacity), _renderer(cfg, f.capacity)
    try:
        before, _ = draw(r, f, cam)
        first = r.pick(100, 75)
        second = r.pick(30, 140)  # a second block elsewhere: its own parameters again
        after, _ = draw(r, f, cam)
        draw(fresh, f, cam)
        want = fresh.pick(30, 140)
    finally:
        r.close()
        fresh.close()
    assert np.array_equal(before, after)
    assert first is not None and second is not None and second != first and second == want


def test_the_plane_test_is_kept_until_planes_or_bounds_change():
    """``BatchBounds.culled`` under a still camera tests again only rewritten batches, and
    its answer is always that of a fresh BatchBounds: after a batch moved into view, after
    the camera moved, and after it moved back."""
    f = _scene()
    west = Camera(**WEST, near=1, far=200, fov_deg=40).frustum_planes(240, 180, f.origin)
    east = Camera(**EAST, near=1, far=200, fov_deg=40).frustum_planes(240, 180, f.origin)
    bb = batches.BatchBounds()

    def check(planes):
        fresh = batches.BatchBounds()
        fresh.note(f)
        want = fresh.culled(f, planes, rel=1e-5)
        got = bb.culled(f, planes, rel=1e-5)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
        return set(got[0].tolist())

    f.dirty = None
    bb.note(f)
    culled_west = check(west)
    # an eastern batch (a full one), culled from the west: move its points into view
    last = max(k for k in culled_west if (k + 1) * 256 <= f.capacity)
    f.positions[last * 256:(last + 1) * 256] = f.positions[:256]
    f.dirty = [(last * 256, (last + 1) * 256)]
    bb.note(f)
    assert last not in check(west)
    f.dirty = []
    bb.note(f)
    culled_east = check(east)
    assert culled_east != culled_west and check(west) == culled_west - {last}


@pytest.mark.parametrize("method", METHODS)
def test_a_frame_in_flight_reads_its_own_points(method):
    """One set of point buffers (``renderer.DATA_SETS``): the next frame's upload is queued
    behind the frame in flight. A large frame is submitted and, without waiting, the next one
    overwrites every position with NaN: the first frame's counters (read once the GPU is
    done) still see only its own finite points, the second's only NaN."""
    require_adapter()
    from pointflow.render.wgpu_tier import renderer as wr
    assert wr.DATA_SETS == 1
    n = 1_000_000
    rng = np.random.default_rng(3)
    w = rng.uniform(-40, 40, (n, 3)) * [1, 1, 0.1]
    f = make_frame(w, intensity=rng.uniform(0, 1, n).astype(np.float32))
    cam = Camera(eye=[0.0, -90.0, 60.0], target=[0.0, 0.0, 0.0], near=1, far=400, fov_deg=50)
    cfg = render_cfg(size=[320, 240], point_size=2, color_by="intensity", raster=method)
    r = _renderer(cfg, n)
    try:
        first = r.render(f, cam)
        nan = dataclasses.replace(f, positions=np.full_like(f.positions, np.nan), dirty=[(0, n)])
        second = r.render(nan, cam)  # no wait between: the first frame may still be drawing
        assert second.uploaded_bytes >= n * 12
        for _ in range(2):  # each waits for the frame two before it: the counters of both
            r.render(dataclasses.replace(nan, dirty=[]), cam)
    finally:
        r.close()
    assert first.extra["removed_nonfinite"] == 0 and first.extra["occupied"] == n
    assert first.drawn > n // 2
    assert second.extra["removed_nonfinite"] == n and second.drawn == 0
