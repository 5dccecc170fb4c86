"""A georeferenced map far from the live points, in every tier (issue 37): the map (UTM-sized
coordinates, written and read back by laspy) in a real map region, a street of live points at
the origin, no ``frames:`` block. The auto view frames the map and says how far apart the two
are; the auto camera, a camera 600 m above the map and an oblique one each light the pixels
that laspy's own points light (an occupancy picture made here from laspy's read with the draw
rules' footprints), within 1 % of the lit pixels; near and far follow what lies in front of
the camera. And a depth-precision check: two points 1 cm apart, 5 km away, are ordered right
in every tier."""
from __future__ import annotations

import types

import numpy as np
import pytest

from pointflow.config import RenderConfig
from pointflow.render import mapregion as mr
from pointflow.render.base import FrameInput
from pointflow.render.camera import APART_FACTOR, Camera, clip_planes, project_to_pixels
from pointflow.render.maplayer import MapLayer
from pointflow.render.view.controller import CameraController
from pointflow.render.rules import footprint_box

from .mapfiles import laspy_points, write_las
from .test_one_picture_layer import TIERS, MapSide, _ctx, _wait_version, tier_renderer, tmp_ipc  # noqa: F401

W, H = 320, 180
UTM = np.array([512_000.0, 6_600_000.0, 120.0])  # a UTM zone's easting and northing (metres)
#: lit pixels of a tier against laspy's occupancy picture: at most this share apart
BOUND = 0.01


def _map_points(tmp_path) -> np.ndarray:
    """40,000 points of a 400 x 400 m tile at UTM coordinates, written by laspy, read back by laspy."""
    from .mapfiles import terrain

    path = write_las(str(tmp_path / "utm.las"), 40_000, seed=5, pos=terrain(40_000, 5) - [700000.0, 5700000.0, 100.0] + UTM)
    return laspy_points(path)["positions"]


def _live_frame(n: int, capacity: int) -> FrameInput:
    """A street of live points around the origin (a sensor that was never placed in the map)."""
    rng = np.random.default_rng(2)
    pos = np.full((capacity, 3), np.nan, np.float32)
    pos[:n] = rng.uniform(-25, 25, (n, 3)) * [1, 1, 0.1]
    return FrameInput(positions=pos, importance=np.ones(capacity, np.float32), t_ingest_ms=np.zeros(capacity),
                      channels={}, head=0, size=n, capacity=capacity, origin=np.zeros(3), now_ms=1000.0,
                      dirty=None, seq=1)


def occupancy(world: np.ndarray, cam: Camera, point_size: float, W: int = W, H: int = H) -> np.ndarray:
    """The pixels laspy's points cover, by the draw rules' square footprint (float64 all through;
    no depth: every point in the frustum lights its pixels)."""
    px, py, depth, w = project_to_pixels(world - cam.target, cam.view_proj(W, H, cam.target), W, H)
    inside = (w > 0) & (np.abs(depth - 0.5) <= 0.5)
    x0, x1, y0, y1 = footprint_box(px[inside], py[inside], point_size / 2, False, W, H)
    img = np.zeros((H, W), bool)
    for dy in range(int(np.ceil(point_size)) + 1):
        for dx in range(int(np.ceil(point_size)) + 1):
            ok = (x0 + dx < x1) & (y0 + dy < y1)
            img[(y0 + dy)[ok], (x0 + dx)[ok]] = True
    return img


def _lit(img: np.ndarray, bg) -> np.ndarray:
    return (img[..., :3] != bg).any(axis=-1)


@pytest.mark.parametrize("tier", TIERS)
def test_a_map_far_from_the_live_points_is_framed_and_not_clipped(tier, tmp_ipc, tmp_path):
    world = _map_points(tmp_path)
    R, S = 4000, world.shape[0]
    cfg, ctx = _ctx(tmp_ipc, S)
    rcfg = RenderConfig(size=(W, H), point_size=2.0)
    layer = MapLayer(cfg, ctx, R)
    side = MapSide(tmp_ipc, S, ctx)
    renderer = None
    try:
        slots = np.arange(S)
        side.region.positions[slots] = world
        side.region.file[slots] = 0
        side.push.send(mr.encode({
            "type": "version", "version": 1, "full": True, "region": side.region.path, "slots": S,
            "channels": [list(c) for c in side.region.channels], "files": ["/data/utm.las"],
            "origin": list(UTM + 200), "set": [[0, S]], "cleared": [], "points": S, "nodes": 1,
            "channel_ranges": {}, "bounds": [world.min(axis=0).tolist(), world.max(axis=0).tolist()]}))
        _wait_version(layer, 1)
        frame = layer.compose(_live_frame(3000, R))
        assert frame.live_slots == R and frame.map_box is not None

        # the auto camera frames the map, and knows how far apart the two are
        auto = CameraController(types.SimpleNamespace(render=rcfg), W, H)
        cam = auto.update(frame)
        assert auto.apart_m > APART_FACTOR * 600 and abs(auto.apart_m - np.linalg.norm(UTM[:2])) < 1000
        assert np.linalg.norm(cam.target - world.mean(axis=0)) < 300, "the auto view looks at the map"

        top = Camera(eye=UTM + [200, 200, 600], target=UTM + [200, 200, 0], up=[0, 1, 0])
        oblique = Camera(eye=UTM + [-300, -300, 350], target=UTM + [200, 200, 0])
        cams = {"auto": cam}
        for name, c in (("top", top), ("oblique", oblique)):
            c.near, c.far = auto.planes(c.eye, c.target, c.up, c.fov_deg)
            cams[name] = c
        # near and far hold the map as seen from the eye, not the whole scene's 6,600 km
        assert 200 < cams["top"].near < 600 and 600 < cams["top"].far < 1000, (cams["top"].near, cams["top"].far)
        assert cams["oblique"].far < 2000

        renderer = tier_renderer(tier, rcfg, R + S, [])
        bg = np.round(np.asarray(rcfg.background[:3]) * 255).astype(np.uint8)
        for name, c in cams.items():
            for _ in range(2):  # the second frame has the map's own origin (the camera looked there)
                f = layer.compose(_live_frame(3000, R))
                renderer.render(f, c)
                layer.drawn(c)
            assert np.array_equal(layer.origin, layer.map_origin)
            got = _lit(renderer.read_image(), bg)
            want = occupancy(world, c, rcfg.point_size)
            share = want.mean()
            assert share > 0.05, f"{name}: a real picture of the map ({share:.1%} of pixels)"
            diff = (got != want).mean()
            assert diff <= BOUND * share, f"{name}: {got.mean():.2%} lit, laspy's picture {share:.2%}, {diff:.3%} differ"
    finally:
        if renderer is not None:
            renderer.close()
        layer.close()
        side.close()


@pytest.mark.parametrize("tier", TIERS)
def test_two_points_a_centimetre_apart_five_km_away_are_ordered(tier):
    """A red point 1 cm in front of a blue one, both 5 km from the origin and from the eye, the
    eye at the origin amid live points 1 m away (so near is small and far is 5 km: the ratio
    that hyperbolic 24-bit depth cannot resolve, as the gl tier had it). The red one wins the
    pixel whichever slot order they have (ties would go to the lower slot)."""
    far = np.array([5000.0, 0.0, 0.0])
    near_pts = np.array([[1.0, 0.5, 0.2], [1.2, -0.5, -0.2]])
    for order in ((0, 1), (1, 0)):
        pts = np.array([far - [0.01, 0, 0], far])[list(order)]  # red 1 cm nearer the eye
        cols = np.array([[255, 0, 0], [0, 0, 255]], np.uint8)[list(order)]
        world = np.concatenate([pts, near_pts])
        rgb = np.concatenate([cols, np.full((2, 3), 200, np.uint8)])
        cap = 4
        frame = FrameInput(positions=world.astype(np.float32), importance=np.ones(cap, np.float32),
                           t_ingest_ms=np.zeros(cap), channels={"rgb": rgb}, head=0, size=cap, capacity=cap,
                           origin=np.zeros(3), now_ms=0.0, dirty=None, seq=1)
        eye, target, up = np.zeros(3), far, np.array([0.0, 0.0, 1.0])
        near, far_plane = clip_planes(eye, target, up, 1.0, W / H, [(world.min(axis=0), world.max(axis=0))])
        assert near < 0.6 and far_plane >= 5000
        cam = Camera(eye=eye, target=target, up=up, fov_deg=1.0, near=near, far=far_plane)
        renderer = tier_renderer(tier, RenderConfig(size=(W, H), color_by="rgb", point_size=5.0), cap, ["rgb"])
        try:
            renderer.render(frame, cam)
            img = renderer.read_image()
            assert tuple(img[H // 2, W // 2, :3]) == (255, 0, 0), f"slot order {order}: {img[H // 2, W // 2]}"
        finally:
            renderer.close()
