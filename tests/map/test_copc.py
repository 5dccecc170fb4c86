"""COPC through its own hierarchy: the nodes are the file's nodes, and exactly its points."""
from __future__ import annotations

import laspy
import numpy as np

from pointflow.map import open_map

from .mapfiles import all_nodes, laspy_points, write_copc


def test_copc_nodes_are_the_files_nodes_and_points(tmp_path):
    path = write_copc(str(tmp_path / "t.copc.laz"), 40_000, seed=1, depth=4)
    with open_map(path, cache_dir=str(tmp_path / "cache"), progress=False) as m:
        assert m.files[0].kind == "copc"
        assert not (tmp_path / "cache").exists()  # no index: COPC is read in place
        assert m.point_count == 40_000
        got, loads = all_nodes(m)
        want = laspy_points(path)
        for name in want:
            assert np.array_equal(got[name], want[name]), name
        # the same keys and counts as laspy's reader of the hierarchy
        with laspy.CopcReader.open(path) as r:
            for key, d in loads:
                assert m.decoded_bytes(key) == sum(a.nbytes for a in d.values())
                _, depth, x, y, z = key
                assert depth <= 3
                pts = r.query(level=depth, bounds=laspy.copc.Bounds(m.node(key).lo, m.node(key).hi))
                # laspy's query keeps points on shared faces twice; ours are the node's own
                assert d["positions"].shape[0] <= len(pts)
        root = m.root_keys()[0]
        assert m.node(root).depth == 0
        for k in m.children(root):
            assert k[1] == 1 and m.node(k).spacing == m.node(root).spacing / 2


def test_copc_and_las_in_one_map(tmp_path):
    from .mapfiles import write_las

    c = write_copc(str(tmp_path / "a.copc.laz"), 5_000, seed=2)
    las = write_las(str(tmp_path / "b.laz"), 5_000, seed=3)
    with open_map([c, las], cache_dir=str(tmp_path / "cache"), progress=False) as m:
        assert [f.kind for f in m.files] == ["copc", "lod"]
        assert m.point_count == 10_000
        assert sum(m.load(k)["positions"].shape[0] for k in m.keys()) == 10_000
