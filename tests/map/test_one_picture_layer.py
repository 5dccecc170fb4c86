"""One picture, at the render stage's map layer: live ring points and map points composed into
one frame (render/maplayer.py) draw exactly the picture of one ring holding both, in every
tier; picking names the map file or the live source. The map side is a real map region
written by :class:`pointflow.render.mapregion.MapRegion` and a real ZeroMQ version message."""
from __future__ import annotations

import dataclasses
import logging
import os
import sys
import tempfile
import time
import types
import uuid

import numpy as np
import pytest
import zmq

sys.path.insert(0, os.path.dirname(os.path.dirname(__file__)))

from gpu_util import require_adapter, require_egl  # noqa: E402

from pointflow.config import EdlConfig, EndpointsConfig, RenderConfig  # noqa: E402
from pointflow.render import mapregion as mr  # noqa: E402
from pointflow.render.base import FrameInput  # noqa: E402
from pointflow.render.camera import Camera  # noqa: E402
from pointflow.render.maplayer import MapLayer, occupied_ranges, xor_ranges  # noqa: E402

TIERS = ["cpu", "cpu-compute", "gl", "wgpu-quads", "wgpu-compute"]
ORIGIN = np.array([500_000.0, 4_000_000.0, 100.0])  # georeferenced: float32 alone would lose it


def tier_renderer(tier: str, cfg: RenderConfig, capacity: int, channels):
    if tier == "cpu":
        from pointflow.render.cpu import CpuRenderer as cls
    elif tier == "cpu-compute":
        from pointflow.render.cpu_compute import CpuComputeRenderer as cls
    elif tier == "gl":
        require_egl().release()
        from pointflow.render.gl import GlRenderer as cls
    else:
        require_adapter()
        from pointflow.render.wgpu_tier import WgpuRenderer as cls
        cfg = dataclasses.replace(cfg, raster=tier[5:])
    return cls(cfg, capacity, list(channels))


def _ctx(tmp: str, slots: int, sources=("lidar",)):
    """The parts of a StageContext the layer uses, with real ipc sockets."""
    ep = EndpointsConfig(map=f"ipc://{tmp}/map.sock", map_camera=f"ipc://{tmp}/map-camera.sock")
    cfg = types.SimpleNamespace(map=types.SimpleNamespace(point_budget=slots),
                                sources=[types.SimpleNamespace(name=n) for n in sources])
    ctx = types.SimpleNamespace(zmq=zmq.Context.instance(), endpoints=ep, log=logging.getLogger("test"))
    return cfg, ctx


def _scene(n_live: int, n_map: int, seed: int = 3):
    rng = np.random.default_rng(seed)
    live = ORIGIN + rng.uniform(-20, 20, (n_live, 3)) * [1, 1, 0.2]
    mapw = ORIGIN + rng.uniform(-30, 30, (n_map, 3)) * [1, 1, 0.2]
    return live, rng.uniform(0, 100, n_live).astype(np.float32), mapw, rng.uniform(0, 100, n_map).astype(np.float32)


def _ring_frame(world: np.ndarray, inten: np.ndarray, capacity: int, head: int = 0) -> FrameInput:
    n = world.shape[0]
    slots = (head + np.arange(n)) % capacity
    pos = np.zeros((capacity, 3), np.float32)
    pos[slots] = (world - ORIGIN).astype(np.float32)
    ch = np.zeros(capacity, np.float32)
    ch[slots] = inten
    rng = (float(inten.min()), float(inten.max())) if n else None
    return FrameInput(positions=pos, importance=np.ones(capacity, np.float32), t_ingest_ms=np.zeros(capacity),
                      channels={"intensity": ch}, head=head, size=n, capacity=capacity, origin=ORIGIN.copy(),
                      now_ms=1000.0, channel_ranges={"intensity": rng} if rng else {}, dirty=None, seq=1)


class MapSide:
    """What the map stage does, by hand: a region, points in some slots, a version message."""

    def __init__(self, tmp: str, slots: int, ctx):
        self.region = mr.MapRegion.create(tmp, slots, [mr.channel_spec("intensity")])
        self.push = ctx.zmq.socket(zmq.PUSH)
        self.push.setsockopt(zmq.LINGER, 0)
        self.push.connect(ctx.endpoints.map)
        self.pull = ctx.zmq.socket(zmq.PULL)
        self.pull.setsockopt(zmq.LINGER, 0)
        self.pull.bind(ctx.endpoints.map_camera)
        self.version = 0

    def put(self, slots: np.ndarray, world: np.ndarray, inten: np.ndarray, cleared=(), full=False) -> None:
        self.region.positions[slots] = world
        self.region.channel["intensity"][slots] = inten
        self.region.file[slots] = 0
        self.version += 1
        self.push.send(mr.encode({
            "type": "version", "version": self.version, "full": full, "region": self.region.path,
            "slots": self.region.slots, "channels": [list(c) for c in self.region.channels],
            "files": ["/data/tile.laz"], "origin": list(ORIGIN + 1.5), "set": mr.runs(np.sort(slots)),
            "cleared": list(cleared), "points": int(len(slots)), "nodes": 1,
            "channel_ranges": {"intensity": [float(inten.min()), float(inten.max())]}}))

    def messages(self, timeout_s: float = 10.0, until=None) -> list:
        """What the layer sent: until ``until(messages)`` holds (or, without one, until a
        pause after the first), at most ``timeout_s`` (generous: a loaded machine)."""
        out, end = [], time.monotonic() + timeout_s
        while time.monotonic() < end:
            if self.pull.poll(50):
                out.append(mr.decode(self.pull.recv()))
                if until is not None and until(out):
                    break
            elif out and until is None:
                break
        return out

    def close(self):
        self.push.close(0)
        self.pull.close(0)
        self.region.close()


def _wait_version(layer: MapLayer, v: int) -> None:
    end = time.monotonic() + 60
    while layer.version < v and time.monotonic() < end:
        layer.poll()
        time.sleep(0.01)
    assert layer.version == v


@pytest.fixture
def tmp_ipc():
    d = tempfile.mkdtemp(prefix="pf-map-", dir=os.environ.get("XDG_RUNTIME_DIR"))
    yield d
    import shutil

    shutil.rmtree(d, ignore_errors=True)


@pytest.mark.parametrize("tier", TIERS)
def test_map_and_live_points_draw_the_picture_of_one_ring(tier, tmp_ipc):
    """Live points in a wrapped ring + map points in scattered map slots, composed by the
    layer, draw pixel for pixel what one ring holding all of them draws (depth, colour by
    intensity over the union range, EDL); picks find both kinds, named."""
    R, S = 4000, 3000
    live, li, mapw, mi = _scene(2500, 2000)
    cfg, ctx = _ctx(tmp_ipc, S)
    rcfg = RenderConfig(size=(320, 200), color_by="intensity", point_size=3.0, edl=EdlConfig(enabled=True))
    layer = MapLayer(cfg, ctx, R)
    side = MapSide(tmp_ipc, S, ctx)
    renderer = ref = None
    try:
        assert side.messages(until=lambda m: m)[0]["type"] == "hello"
        slots = np.sort(np.random.default_rng(1).choice(S, 2000, replace=False))
        side.put(slots, mapw, mi, full=True)
        _wait_version(layer, 1)
        ring = _ring_frame(live, li, R, head=3000)  # wraps around the end of the ring
        frame = layer.compose(ring)
        assert frame.capacity == R + S and frame.size == R + S
        assert frame.channel_ranges["intensity"] == (float(min(li.min(), mi.min())), float(max(li.max(), mi.max())))
        cam = Camera.fit(ORIGIN - [30, 30, 6], ORIGIN + [30, 30, 6], aspect=320 / 200)
        renderer = tier_renderer(tier, rcfg, R + S, ["intensity"])
        renderer.render(frame, cam)
        layer.drawn()
        img = renderer.read_image()

        both = np.concatenate([live, mapw])
        # picking: a map point and a live point, each named
        vp = cam.view_proj(320, 200)
        def pix(p):
            c = vp @ np.append(p, 1.0)
            return (c[0] / c[3] + 1) * 160, (1 - c[1] / c[3]) * 100
        d = np.linalg.norm(both - cam.eye, axis=1)  # the nearest points are on top
        kinds = set()
        order = np.argsort(d)
        nearest = np.concatenate([order[order < len(live)][:20], order[order >= len(live)][:20]])
        for i in nearest:
            x, y = pix(both[i])
            slot = renderer.pick(x, y)
            if slot is None:
                continue
            rep = layer.pick_reply(_FakeRing(live, li, R, 3000), slot, _to_dict)
            assert rep["point"] is not None
            kinds.add(rep["source"])
            if rep["source"].startswith("map: "):
                assert rep["source"] == "map: /data/tile.laz"
                j = int(slot) - R
                assert np.allclose(rep["point"]["position"], side.region.positions[j])  # float64 world, exact
        assert kinds == {"map: /data/tile.laz", "lidar"}

        ref = tier_renderer(tier, rcfg, both.shape[0], ["intensity"])
        ref.render(_ring_frame(both, np.concatenate([li, mi]), both.shape[0]), cam)
        want = ref.read_image()
        covered = (want[..., :3] != 0).any(axis=-1).mean()
        assert covered > 0.05  # a real picture, not an empty one
        assert np.array_equal(img, want), f"{(img != want).any(axis=-1).mean():.4%} of pixels differ"

        # the layer acknowledged the version and told the map stage where the view looks
        layer.publish([("main", cam, 320, 200)])
        msgs = side.messages(until=lambda m: any(x["type"] == "cameras" for x in m)
                             and any(x["type"] == "ack" for x in m))
        assert {"type": "ack", "version": 1} in [{k: m[k] for k in ("type", "version") if k in m} for m in msgs]
        cams = [m for m in msgs if m["type"] == "cameras"]
        assert cams and cams[-1]["views"][0]["view"] == "main"
        assert np.allclose(cams[-1]["views"][0]["eye"], cam.eye)
    finally:
        for r in (renderer, ref):
            if r is not None:
                r.close()
        layer.close()
        side.close()


class _FakeRing:
    """``get_point`` of a ring holding ``world`` from ``head`` (the layer only reads that)."""

    def __init__(self, world, inten, capacity, head):
        self.world, self.inten, self.cap, self.head = world, inten, capacity, head

    def get_point(self, slot):
        i = (int(slot) - self.head) % self.cap
        if i >= len(self.world):
            return None
        return types.SimpleNamespace(slot=slot, position=self.world[i], channels={"intensity": float(self.inten[i])},
                                     t_ingest_ms=0.0, generation=1, importance=1.0)


def _to_dict(rec):
    from pointflow.render.view.protocol import point_to_dict

    return point_to_dict(rec)


def test_map_versions_update_only_what_changed_and_clear_what_left(tmp_ipc):
    """A second version sets new slots and clears old ones: the composed frame's dirty ranges
    are exactly those (offset past the ring), cleared slots are empty (NaN), the ring's own
    dirty ranges pass through, and a frame composed but not drawn keeps its changes."""
    R, S = 100, 50
    cfg, ctx = _ctx(tmp_ipc, S)
    layer = MapLayer(cfg, ctx, R)
    side = MapSide(tmp_ipc, S, ctx)
    try:
        live, li, mapw, mi = _scene(40, 30)
        side.put(np.arange(30), mapw, mi, full=True)
        _wait_version(layer, 1)
        f = layer.compose(_ring_frame(live, li, R))
        assert f.dirty is None
        assert np.isfinite(f.positions[R:R + 30]).all() and np.isnan(f.positions[R + 30:]).all()
        assert np.isnan(f.positions[40:R]).all()  # free ring slots are empty
        layer.drawn()
        side.put(np.arange(30, 40), mapw[:10], mi[:10], cleared=[(0, 5)])
        _wait_version(layer, 2)
        ring = _ring_frame(live, li, R)
        ring.dirty = [(10, 12)]
        f = layer.compose(ring)
        assert f.dirty == [(10, 12), (R, R + 5), (R + 30, R + 40)]
        assert np.isnan(f.positions[R:R + 5]).all() and np.isfinite(f.positions[R + 5:R + 40]).all()
        assert layer.points == 10 and f.budget is None
        # not drawn (e.g. no camera yet): the next frame still carries those ranges
        ring.dirty = []
        f = layer.compose(ring)
        assert f.dirty == [(10, 12), (R, R + 5), (R + 30, R + 40)]
        layer.drawn()
        f = layer.compose(ring)
        assert f.dirty == []
        # the ring evicts by age: head moves, nothing written; the freed slots are blanked
        ring.head, ring.size = 10, 30
        f = layer.compose(ring)
        assert f.dirty == [(0, 10)] and np.isnan(f.positions[0:10]).all()
    finally:
        layer.close()
        side.close()


def test_range_helpers():
    assert occupied_ranges(8, 4, 10) == [(8, 10), (0, 2)]
    assert occupied_ranges(0, 10, 10) == [(0, 10)]
    assert occupied_ranges(3, 0, 10) == []
    assert xor_ranges([(0, 5)], [(2, 7)]) == [(0, 2), (5, 7)]
    assert mr.runs(np.array([1, 2, 3, 7, 9, 10])) == [(1, 4), (7, 8), (9, 11)]


def test_the_render_stage_publishes_every_views_camera_main_first(tmp_ipc):
    """``publish_stage`` sends the main view's camera and the view server's views' (the hub of
    render/view/hub.py), main first; an unchanged set is not sent again."""
    cfg, ctx = _ctx(tmp_ipc, 10)
    layer = MapLayer(cfg, ctx, 10)
    side = MapSide(tmp_ipc, 10, ctx)
    try:
        a = Camera(eye=[0.0, -10.0, 5.0], target=[0.0, 0.0, 0.0])
        b = Camera(eye=[3.0, -10.0, 5.0], target=[1.0, 0.0, 0.0])
        view = types.SimpleNamespace(last=a, cfg=types.SimpleNamespace(render=types.SimpleNamespace(size=(640, 360))))
        hub = types.SimpleNamespace(views={"tab1": types.SimpleNamespace(ctl=types.SimpleNamespace(last=b),
                                                                          width=300, height=200)})
        stage = types.SimpleNamespace(window=None, view=view, hub=hub, renderer=None)
        layer.publish_stage(stage)
        cams = [m for m in side.messages(until=lambda m: any(x["type"] == "cameras" for x in m))
                if m["type"] == "cameras"]
        assert len(cams) == 1
        views = cams[0]["views"]
        assert [v["view"] for v in views] == ["main", "tab1"]
        assert (views[0]["width"], views[0]["height"], views[1]["width"], views[1]["height"]) == (640, 360, 300, 200)
        assert np.allclose(views[1]["eye"], b.eye)
        time.sleep(0.15)
        layer.publish_stage(stage)  # nothing moved: nothing sent
        assert not [m for m in side.messages(timeout_s=0.5) if m["type"] == "cameras"]
    finally:
        layer.close()
        side.close()
