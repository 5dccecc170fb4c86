"""A LAS/LAZ/PLY/PCD file read through its level-of-detail index (see :mod:`.build`): the
index is used while it matches the file (size, mtime, header checksum) and this build's
:data:`~.build.INDEX_VERSION`; otherwise it is built again here, with a warning that says why."""
from __future__ import annotations

import json
import logging
import os
from typing import Optional

import numpy as np

from .build import INDEX_VERSION, build_index, dtype_from_json, index_dir
from .errors import MapError
from .inputs import _LasInput, file_identity, header_bytes_of, map_format

log = logging.getLogger(__name__)


class LodFile:
    """A LAS/LAZ/PLY/PCD file through its index (built or rebuilt here when missing or stale)."""

    kind = "lod"

    def __init__(self, path: str, cache_dir: Optional[str] = None, progress=None, preview=None,
                 preview_points: int = 0):
        self.path = path
        map_format(path)
        self.dir = index_dir(path, cache_dir)
        why = self._stale()
        if why:
            if why != "no index yet":
                log.warning("%s: rebuilding its level-of-detail index (%s)", path, why)
            build_index(path, self.dir, progress, preview, preview_points)
            why = self._stale()
            if why:
                raise MapError(path, f"its fresh level-of-detail index in {self.dir} does not check out: {why}")
        self._open()

    def _stale(self) -> Optional[str]:
        """Why the index in :attr:`dir` cannot be used (None: it can)."""
        try:
            with open(os.path.join(self.dir, "meta.json")) as f:
                meta = json.load(f)
        except FileNotFoundError:
            return "no index yet"
        except (OSError, ValueError) as exc:
            return f"its meta.json does not read: {type(exc).__name__}"
        if not isinstance(meta, dict) or meta.get("version") != INDEX_VERSION:
            return f"index format version {meta.get('version') if isinstance(meta, dict) else '?'}, this build reads {INDEX_VERSION}"
        try:
            ident = file_identity(self.path, header_bytes_of(self.path))
        except OSError as exc:
            raise MapError(self.path, f"cannot read: {exc.strerror or exc}") from None
        if meta.get("identity") != ident:
            return "the file changed since the index was built"
        try:
            dt = dtype_from_json(meta["dtype"])
            nodes = np.load(os.path.join(self.dir, "nodes.npy"), allow_pickle=False)
            size = os.path.getsize(os.path.join(self.dir, "points.bin"))
        except (OSError, ValueError, KeyError, TypeError) as exc:
            return f"its files do not read: {type(exc).__name__}: {exc}"
        count = int(meta.get("count", -1))
        if size != count * dt.itemsize or int(nodes["count"].sum()) != count:
            return f"its points.bin has {size} bytes for {count} points of {dt.itemsize} bytes"
        self._meta, self._dtype, self._table = meta, dt, nodes
        return None

    def _open(self) -> None:
        meta = self._meta
        self.point_count = int(meta["count"])
        self.cube_lo = np.asarray(meta["cube_lo"], np.float64)
        self.cube_side = float(meta["cube_side"])
        self.grid = 1 << int(meta["grid_bits"])
        self.bounds = (np.asarray(meta["bounds"][0], np.float64), np.asarray(meta["bounds"][1], np.float64))
        t = self._table
        self.nodes = {(int(d), int(x), int(y), int(z)): (int(o), int(c), int(c))
                      for d, x, y, z, o, c in zip(t["d"], t["x"], t["y"], t["z"], t["offset"], t["count"])}
        self._fd = os.open(os.path.join(self.dir, "points.bin"), os.O_RDONLY)
        if meta["kind"] == "las":
            inp = _LasInput(self.path)
            if inp.dtype != self._dtype:
                raise MapError(self.path, "its point format differs from its index's")
            self.point_format, self.scales, self.offsets = inp.point_format, inp.scales, inp.offsets
            from .lasrec import las_channel_names

            self.channels = las_channel_names(self.point_format)
        else:
            self.channels = [n for n in self._dtype.names if n not in ("x", "y", "z")]

    @property
    def bytes_per_point(self) -> int:
        """Bytes a decoded point takes: positions (3 float64) and each channel."""
        from .lasrec import LAS_CHANNEL_BYTES

        if self._meta["kind"] == "las":
            return 24 + sum(LAS_CHANNEL_BYTES[c] for c in self.channels)
        return 24 + sum(self._dtype.fields[c][0].itemsize for c in self.channels)

    def spacing(self, depth: int) -> float:
        return self.cube_side / (1 << depth) / self.grid

    def load(self, key: tuple) -> dict[str, np.ndarray]:
        try:
            off, _, count = self.nodes[key]
        except KeyError:
            raise KeyError(f"{self.path}: no node {key}") from None
        isz = self._dtype.itemsize
        raw = os.pread(self._fd, count * isz, off * isz)
        if len(raw) != count * isz:
            raise MapError(self.path, f"node {key}: its index file {self.dir}/points.bin is cut short")
        recs = np.frombuffer(raw, self._dtype)
        if self._meta["kind"] == "las":
            from .lasrec import las_points

            return las_points(recs, self.point_format, self.scales, self.offsets)
        out = {"positions": np.column_stack([recs["x"], recs["y"], recs["z"]]).astype(np.float64)}
        for name in self.channels:
            out[name] = recs[name].copy()
        return out

    def close(self) -> None:
        fd, self._fd = getattr(self, "_fd", None), None
        if fd is not None:
            os.close(fd)
