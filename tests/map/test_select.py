"""Node selection by projected size within a budget, and a bounded cache on a camera flight."""
from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from pointflow.map import NodeCache, open_map, select_nodes
from pointflow.map.cache import node_bytes
from pointflow.render.camera import Camera, project_to_pixels

from .mapfiles import ORIGIN, write_las

W, H = 640, 480


@pytest.fixture(scope="module")
def big(tmp_path_factory):
    d = tmp_path_factory.mktemp("sel")
    path = write_las(str(d / "t.laz"), 200_000, seed=21)
    m = open_map(path, cache_dir=str(d / "cache"), progress=False)
    yield m
    m.close()


def in_view(m, cam):
    """Every point of the map that the camera's frustum holds (x, y in [-w, w], depth in [0, 1])."""
    keys, inside = [], []
    vp = cam.view_proj(W, H)
    for k in m.keys():
        p = m.load(k)["positions"]
        px, py, depth, w = project_to_pixels(p, vp, W, H)
        ok = (w > 0) & (px >= 0) & (px < W) & (py >= 0) & (py < H) & (depth >= 0) & (depth <= 1)
        keys.append(k)
        inside.append(int(ok.sum()))
    return dict(zip(keys, inside))


def close_camera():
    return Camera(eye=ORIGIN + [90.0, 90.0, 40.0], target=ORIGIN + [110.0, 100.0, 0.0], near=0.5, far=2000.0)


def test_budget_above_points_in_view_gives_every_point_in_view(big):
    cam = close_camera()
    counts = in_view(big, cam)
    needed = {k for k, c in counts.items() if c}
    assert 0 < len(needed) < len(counts)  # the camera sees part of the map
    total_in_view_nodes = sum(big.node(k).count for k in needed)
    sel = select_nodes(big, cam.view_proj(W, H), (W, H), cam.eye, total_in_view_nodes * 2)
    assert needed <= set(sel), "a node with points in view was not selected"
    assert len(sel) == len(set(sel))
    # frustum culling dropped nodes wholly outside (the budget would have allowed them all)
    assert len(sel) < len(counts)


def test_coarse_first_and_within_budget(big):
    cam = Camera.fit(*big.bounds)
    vp = cam.view_proj(W, H)
    prev = []
    for budget in (15_000, 40_000, 90_000, 400_000):
        sel = select_nodes(big, vp, (W, H), cam.eye, budget)
        assert sum(big.node(k).count for k in sel) <= budget
        seen = set()
        for k in sel:
            if k[1]:
                parent = (k[0], k[1] - 1, k[2] >> 1, k[3] >> 1, k[4] >> 1)
                assert parent in seen, f"{k} before its parent"
            seen.add(k)
        assert sel[:len(prev)] == prev  # a bigger budget refines the same picture further
        prev = sel
    assert sum(big.node(k).count for k in prev) == big.point_count  # the whole map fits 400 k


def test_nearer_nodes_first(big):
    cam = close_camera()
    sel = select_nodes(big, cam.view_proj(W, H), (W, H), cam.eye, 60_000)
    deep = [k for k in sel if k[1] == max(s[1] for s in sel)]
    far_cam = Camera(eye=ORIGIN + [340.0, 340.0, 60.0], target=ORIGIN + [280.0, 280.0, 0.0], near=0.5, far=2000.0)
    sel_far = select_nodes(big, far_cam.view_proj(W, H), (W, H), far_cam.eye, 60_000)
    assert set(sel) != set(sel_far)
    d = [np.linalg.norm((big.node(k).lo + big.node(k).hi) / 2 - cam.eye) for k in deep]
    d_other = [np.linalg.norm((big.node(k).lo + big.node(k).hi) / 2 - far_cam.eye) for k in deep]
    assert np.mean(d) < np.mean(d_other)


def test_nothing_when_looking_away(big):
    cam = Camera(eye=ORIGIN + [200.0, 200.0, 300.0], target=ORIGIN + [200.0, 200.0, 1000.0], near=0.5, far=500.0)
    assert select_nodes(big, cam.view_proj(W, H), (W, H), cam.eye, 10 ** 7) == []


class _Boxes:
    """A map of root nodes only, one per box (what select_nodes reads of a source)."""

    def __init__(self, boxes):
        from types import SimpleNamespace
        self.nodes = {(i, 0, 0, 0, 0): SimpleNamespace(lo=np.asarray(lo, float), hi=np.asarray(hi, float), count=10,
                                                       spacing=1.0) for i, (lo, hi) in enumerate(boxes)}

    def node(self, k):
        return self.nodes[k]

    def root_keys(self):
        return list(self.nodes)

    def children(self, k):
        return []


def test_nodes_are_culled_by_the_planes_that_cull_ring_batches():
    """The map and the render tiers decide a box by one test (render.batches.boxes_outside):
    a box between the eye and the near plane is dropped, as no tier draws its points; a box
    the frustum cuts, and one a hair inside the far plane, are kept."""
    from pointflow.render.batches import boxes_outside
    from pointflow.render.camera import planes_of

    cam = Camera(eye=[0.0, -10.0, 0.0], target=[0.0, 0.0, 0.0], up=[0.0, 0.0, 1.0], near=2.0, far=50.0)
    vp = cam.view_proj(W, H)
    boxes = [([-0.1, -9.5, -0.1], [0.1, -9.0, 0.1]),     # 0.5-1 in front of the eye: before the near plane
             ([-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]),       # in view
             ([-0.1, 39.9, -0.1], [0.1, 40.2, 0.1]),      # cut by the far plane (at y = 40)
             ([-0.1, 40.01, -0.1], [0.1, 41.0, 0.1]),     # beyond it
             ([50.0, 0.0, -1.0], [60.0, 1.0, 1.0]),       # right of the view
             ([-0.1, -12.0, -0.1], [0.1, -11.0, 0.1])]    # behind the eye
    src = _Boxes(boxes)
    got = {k[0] for k in select_nodes(src, vp, (W, H), cam.eye, 10 ** 6)}
    assert got == {1, 2}
    lo, hi = (np.array([b[i] for b in boxes]) for i in (0, 1))
    assert got == set(np.flatnonzero(~boxes_outside(lo, hi, planes_of(vp))))  # the tiers' own test


def test_origin_relative_matrices_select_the_same(big):
    cam = close_camera()
    o = big.origin
    a = select_nodes(big, cam.view_proj(W, H), (W, H), cam.eye, 50_000)
    b = select_nodes(big, cam.view_proj(W, H, origin=o), (W, H), cam.eye - o, 50_000, origin=o)
    assert a == b


def test_memory_bounded_while_flying_over_a_file_20x_the_cache(tmp_path):
    path = write_las(str(tmp_path / "big.laz"), 600_000, seed=22)
    with open_map(path, cache_dir=str(tmp_path / "cache"), progress=False) as m:
        sample = m.load(m.root_keys()[0])
        per_point = node_bytes(sample) / sample["positions"].shape[0]
        decoded = per_point * m.point_count
        cache = NodeCache(int(decoded / 20))
        biggest = max(m.node(k).count for k in m.keys()) * per_point
        assert biggest < cache.max_bytes
        tracemalloc.start()
        base = tracemalloc.get_traced_memory()[0]
        loaded_bytes = 0
        for t in np.linspace(0, 1, 40):
            x, y = 20 + 360 * t, 20 + 360 * (0.5 + 0.45 * np.sin(6 * t))
            cam = Camera(eye=ORIGIN + [x, y, 40.0], target=ORIGIN + [x + 40, y + 10, 0.0], near=0.5, far=3000.0)
            sel = select_nodes(m, cam.view_proj(W, H), (W, H), cam.eye, 80_000, loaded=set(cache.keys()))
            assert sel
            for k in sel:
                if cache.get(k) is None:
                    node = m.load(k)
                    loaded_bytes += node_bytes(node)
                    cache.put(k, node)
                    del node
                assert cache.bytes_used <= cache.max_bytes
        current, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        assert cache.evictions > 0 and cache.hits > 0 and cache.misses > 0
        assert loaded_bytes > 2 * cache.max_bytes  # the flight saw far more than the cache holds
        # what stays allocated is the cache; the peak adds one node being decoded (and its raw bytes)
        assert current - base <= cache.max_bytes + 256 * 1024, (current - base, cache.max_bytes)
        assert peak - base <= cache.max_bytes + 4 * biggest + 1024 * 1024, (peak - base, cache.max_bytes)


def test_decoded_bytes_match_loads_and_a_too_small_cache_is_named(big):
    from pointflow.map import MapError

    for k in big.keys()[:5]:
        assert big.decoded_bytes(k) == node_bytes(big.load(k))
    biggest = max(big.decoded_bytes(k) for k in big.keys())
    big.check_cache(biggest)
    with pytest.raises(MapError, match="more than the whole node cache") as ei:
        big.check_cache(biggest - 1)
    assert big.paths[0] in str(ei.value)
