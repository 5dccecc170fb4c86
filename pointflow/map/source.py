"""One map made of one or more files: node keys, bounds, channels and loads across them.

A key is ``(file index, depth, x, y, z)``: the file's octree key (COPC's VoxelKey, or the
level-of-detail index's) prefixed by which of the map's files it belongs to. Hashable and
JSON-able (a list of ints)."""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Callable, Optional, Sequence, Union

import numpy as np

from .errors import MapError

Key = tuple  # (file index, depth, x, y, z)


@dataclass(frozen=True)
class MapNode:
    key: Key
    lo: np.ndarray      # the node's cube, world float64
    hi: np.ndarray
    count: int          # points held by this node itself (not its children)
    depth: int
    spacing: float      # about how far apart its points are (world units)


class MapSource:
    """The files of a map behind one octree-of-octrees (one root per file)."""

    def __init__(self, files: list):
        self.files = files
        self.paths = [f.path for f in files]
        los = np.array([f.bounds[0] for f in files], np.float64)
        his = np.array([f.bounds[1] for f in files], np.float64)
        self.bounds = (los.min(axis=0), his.max(axis=0))
        #: a float64 origin near the points: positions minus it fit float32 (see docs/map.md)
        self.origin = np.round((self.bounds[0] + self.bounds[1]) / 2.0, 3)
        self.channels = [c for c in files[0].channels if all(c in f.channels for f in files[1:])]
        self.point_count = int(sum(f.point_count for f in files))
        self._children: dict[Key, list[Key]] = {}
        for i, f in enumerate(files):
            for d, x, y, z in f.nodes:
                if d:
                    self._children.setdefault((i, d - 1, x >> 1, y >> 1, z >> 1), []).append((i, d, x, y, z))

    def root_keys(self) -> list[Key]:
        return [(i, 0, 0, 0, 0) for i, f in enumerate(self.files) if (0, 0, 0, 0) in f.nodes]

    def keys(self) -> list[Key]:
        return [(i, *k) for i, f in enumerate(self.files) for k in f.nodes]

    def node(self, key: Key) -> MapNode:
        i, d, x, y, z = key
        f = self.files[i]
        count = f.nodes[(d, x, y, z)][2]
        side = f.cube_side / (1 << d)
        lo = f.cube_lo + np.array([x, y, z], np.float64) * side
        return MapNode(tuple(key), lo, lo + side, int(count), int(d), float(f.spacing(d)))

    def children(self, key: Key) -> list[Key]:
        return list(self._children.get(tuple(key), ()))

    def load(self, key: Key) -> dict[str, np.ndarray]:
        """The node's points, exactly as in the file: ``positions`` (n, 3) float64 world plus
        the file's channels. A node that cannot be read raises :class:`MapError`."""
        i, *k = key
        return self.files[i].load(tuple(k))

    def decoded_bytes(self, key: Key) -> int:
        """About how many bytes ``load(key)`` returns (positions float64 + the channels)."""
        return self.node(key).count * self.files[key[0]].bytes_per_point

    def check_cache(self, max_bytes: int) -> None:
        """A node bigger than the whole node cache could be loaded but never kept (it would be
        read again for every picture): a :class:`MapError` naming the file and the node."""
        for key in self.keys():
            size = self.decoded_bytes(key)
            if size > max_bytes:
                raise MapError(self.paths[key[0]], f"node {list(key[1:])} decodes to {size / 2**20:.1f} MiB, more than "
                                                   f"the whole node cache ({max_bytes / 2**20:.1f} MiB): raise cache_mb")

    def source_name(self, key: Key) -> str:
        return os.path.basename(self.paths[key[0]])

    def close(self) -> None:
        for f in self.files:
            f.close()

    def __enter__(self) -> "MapSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _las_header(path: str):
    """A LAS/LAZ/COPC file's header, checked against the file first (a garbage header makes
    laspy loop for minutes: formats/las.py ``precheck_las``); None for another format or a
    header that does not read (the map stage names that file when it opens it)."""
    import laspy

    from pointflow.formats.las import precheck_las

    if os.path.splitext(path)[1].lower() not in (".las", ".laz"):
        return None
    try:
        precheck_las(path)
        with laspy.open(path) as f:
            return f.header
    except Exception:  # noqa: BLE001 - a broken file is the opener's error, with its name
        return None


def header_bounds(paths: Sequence[str]) -> Optional[tuple[np.ndarray, np.ndarray]]:
    """The files' bounds from their LAS/LAZ/COPC headers, read at once (before any index is
    built), so a view can frame the map from the start; None when a file's header has none
    (PLY, PCD) or does not read (the map stage names that file when it opens it)."""
    los, his = [], []
    for p in paths:
        h = _las_header(p)
        if h is None:
            return None
        lo, hi = np.asarray(h.mins, np.float64), np.asarray(h.maxs, np.float64)
        if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (hi >= lo).all()):
            return None
        los.append(lo)
        his.append(hi)
    return (np.min(los, axis=0), np.max(his, axis=0)) if los else None


def header_units(paths: Sequence[str], log=None) -> Optional[dict]:
    """The map's length units from its LAS/LAZ/COPC headers' CRS (formats/las.py
    ``crs_units``): ``{"xy", "z"}`` for the views' grid, measures and legend; None when a
    file does not say (PLY, PCD, no CRS: the views take metres); empty labels when the files
    disagree (then ``log`` says so)."""
    from pointflow.formats.las import crs_units

    found = []
    for p in paths:
        h = _las_header(p)
        if h is None:
            return None
        u = crs_units(h)
        if u is None:
            return None
        found.append((p, u))
    if not found:
        return None
    if any(u != found[0][1] for _, u in found[1:]):
        if log is not None:
            log.warning("the map's files are in different units (%s): its lengths are shown without a unit",
                        ", ".join(f"{os.path.basename(p)} {u['xy']}" for p, u in found))
        return {"xy": "", "z": ""}
    return found[0][1]


Progress = Union[None, bool, Callable[[int, int], None]]


def open_map(paths: Union[str, os.PathLike, Sequence[Union[str, os.PathLike]]], *, cache_dir: Optional[str] = None,
             progress: Progress = None, preview: Optional[Callable[[int, dict], None]] = None,
             preview_points: int = 0) -> MapSource:
    """Open the files of a map: COPC through its hierarchy; LAS/LAZ/PLY/PCD through a
    level-of-detail index, built at the first open (a progress line on stderr unless
    ``progress`` is False or a callable ``(done, total)``) and kept in ``cache_dir``
    (default: the user cache directory, ``$XDG_CACHE_HOME/pointflow/map``). While an index is
    built, ``preview(file index, points)`` gets an evenly spread share of the points read
    (about ``preview_points`` of all the files), decoded as :meth:`MapSource.load` gives them."""
    from .copc import CopcFile, is_copc
    from .lod import LodFile

    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    paths = [os.fspath(p) for p in paths]
    if not paths:
        raise ValueError("open_map needs at least one path")
    files: list = []
    try:
        for p in paths:
            if not os.path.isfile(p):
                raise MapError(p, "no such file" if not os.path.exists(p) else "not a regular file")
            i = len(files)
            each = (lambda data, i=i: preview(i, data)) if preview is not None else None
            files.append(CopcFile(p) if is_copc(p) else
                         LodFile(p, cache_dir=cache_dir, progress=progress, preview=each,
                                 preview_points=preview_points // len(paths)))
    except BaseException:
        for f in files:
            f.close()
        raise
    return MapSource(files)
