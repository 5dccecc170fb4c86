"""Map files written by real writers for the map tests: laspy (LAS/LAZ), copc-lib (COPC),
plyfile (PLY), the project's PCD writer; and laspy's own read of them to compare against."""
from __future__ import annotations

import numpy as np

ORIGIN = np.array([700000.0, 5700000.0, 100.0])  # UTM-like: float32 cannot hold these to cm


def terrain(n: int, seed: int = 0, size: float = 400.0) -> np.ndarray:
    """An aerial-like surface: x, y uniform over a square, z a smooth hill plus noise."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, size, (n, 2))
    z = 20 * np.sin(xy[:, 0] / 60) * np.cos(xy[:, 1] / 80) + rng.normal(0, 0.3, n)
    return ORIGIN + np.column_stack([xy, z])


def las_record(pos: np.ndarray, point_format: int = 3, seed: int = 0):
    """laspy points with every channel the map keeps, gps_time = the point's index (unique)."""
    import laspy

    n = pos.shape[0]
    rng = np.random.default_rng(seed)
    hdr = laspy.LasHeader(point_format=point_format, version="1.4" if point_format >= 6 else "1.2")
    hdr.scales = np.array([0.01, 0.01, 0.01])
    hdr.offsets = np.floor(pos.min(axis=0)) if n else np.zeros(3)
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = pos[:, 0], pos[:, 1], pos[:, 2]
    las.intensity = rng.integers(0, 65535, n)
    las.classification = rng.integers(0, 10, n)
    las.return_number = rng.integers(1, 4, n)
    las.gps_time = np.arange(n, dtype=np.float64)
    las.red, las.green, las.blue = (rng.integers(0, 65535, n) for _ in range(3))
    return las


def write_las(path: str, n: int, seed: int = 0, point_format: int = 3, pos: np.ndarray | None = None,
              crs: str | None = None) -> str:
    """LAS or LAZ (by the extension; LAZ through lazrs); ``crs`` (e.g. "EPSG:2992") written by
    laspy: a WKT VLR in LAS 1.4, GeoTIFF keys in 1.2."""
    import laspy

    las = las_record(terrain(n, seed) if pos is None else pos, point_format, seed)
    if crs is not None:
        import pyproj

        las.header.add_crs(pyproj.CRS(crs))
    las.write(path, laz_backend=laspy.LazBackend.Lazrs if path.endswith(".laz") else None)
    return path


def write_copc(path: str, n: int, seed: int = 0, depth: int = 4) -> str:
    """A COPC file by copc-lib's writer: each point goes to a random depth < ``depth`` and to the
    node of that depth whose cube holds it (a valid, if unbalanced, COPC octree)."""
    import copclib
    import laspy

    rng = np.random.default_rng(seed)
    pos = terrain(n, seed)
    las = las_record(pos, 7, seed)
    rec = las.points
    xyz = np.column_stack([np.asarray(rec.x), np.asarray(rec.y), np.asarray(rec.z)])
    lo_b, hi_b = xyz.min(axis=0), xyz.max(axis=0)
    half = float((hi_b - lo_b).max()) / 2 + 1.0
    centre = (lo_b + hi_b) / 2
    cfg = copclib.CopcConfigWriter(7, copclib.Vector3(*las.header.scales), copclib.Vector3(*las.header.offsets))
    info = cfg.copc_info
    info.center_x, info.center_y, info.center_z = (float(v) for v in centre)
    info.halfsize, info.spacing = half, 2 * half / 64
    cfg.las_header.min = copclib.Vector3(*(float(v) for v in lo_b))
    cfg.las_header.max = copclib.Vector3(*(float(v) for v in hi_b))
    writer = copclib.FileWriter(path, cfg)
    lvl = rng.integers(0, depth, n)
    lvl[0] = 0  # the root holds at least one point
    lo = centre - half
    for d in range(depth):
        sel = np.flatnonzero(lvl == d)
        q = np.clip(np.floor((xyz[sel] - lo) / (2 * half) * (1 << d)).astype(np.int64), 0, (1 << d) - 1)
        code = (q[:, 0] << 40) | (q[:, 1] << 20) | q[:, 2]
        for c in np.unique(code):
            members = sel[code == c]
            key = copclib.VoxelKey(d, int(c >> 40), int((c >> 20) & 0xFFFFF), int(c & 0xFFFFF))
            raw = np.frombuffer(rec.array[members].tobytes(), np.int8)
            writer.AddNode(key, copclib.VectorChar(raw))
    writer.Close()
    assert laspy.read(path).header.point_count == n
    return path


def write_ply(path: str, n: int, seed: int = 0) -> tuple[np.ndarray, dict]:
    """Binary PLY by plyfile: float64 x, y, z, uint8 rgb, float32 intensity."""
    import plyfile

    rng = np.random.default_rng(seed)
    pos = terrain(n, seed)
    v = np.empty(n, [("x", "f8"), ("y", "f8"), ("z", "f8"), ("red", "u1"), ("green", "u1"), ("blue", "u1"),
                     ("intensity", "f4")])
    v["x"], v["y"], v["z"] = pos.T
    rgb = rng.integers(0, 255, (n, 3)).astype(np.uint8)
    v["red"], v["green"], v["blue"] = rgb.T
    v["intensity"] = rng.random(n).astype(np.float32)
    plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex")]).write(path)
    return pos, {"rgb": rgb, "intensity": v["intensity"].copy()}


def write_pcd(path: str, n: int, seed: int = 0) -> tuple[np.ndarray, dict]:
    from pointflow.formats import write_pcd as _write

    rng = np.random.default_rng(seed)
    pos = (terrain(n, seed) - ORIGIN).astype(np.float32)  # PCD holds float32: local coordinates
    inten = rng.random(n).astype(np.float32)
    _write(path, pos, {"intensity": inten})
    return pos, {"intensity": inten}


def laspy_points(path: str) -> dict[str, np.ndarray]:
    """laspy's own read of a file, in the map's channel names, sorted by gps_time."""
    import laspy

    las = laspy.read(path)
    out = {"positions": np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)]),
           "intensity": np.asarray(las.intensity), "classification": np.asarray(las.classification),
           "return_number": np.asarray(las.return_number), "gps_time": np.asarray(las.gps_time),
           "rgb": np.column_stack([np.asarray(las.red), np.asarray(las.green), np.asarray(las.blue)])}
    order = np.argsort(out["gps_time"], kind="stable")
    return {k: v[order] for k, v in out.items()}


def all_nodes(source) -> tuple[dict[str, np.ndarray], list]:
    """Every node's points concatenated (sorted by gps_time when there is one) and the loads."""
    loads = [(k, source.load(k)) for k in source.keys()]
    cat = {name: np.concatenate([d[name] for _, d in loads]) for name in loads[0][1]}
    if "gps_time" in cat:
        order = np.argsort(cat["gps_time"], kind="stable")
        cat = {k: v[order] for k, v in cat.items()}
    return cat, loads
