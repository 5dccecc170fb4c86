"""A map file as raw records in chunks, for the index build: LAS/LAZ through laspy's chunk
iterator (the file's own packed records), PLY/PCD through the project's readers."""
from __future__ import annotations

import hashlib
import os
import struct
from typing import Iterator

import numpy as np

from ..arrays import column_max, column_min, finite_rows
from .errors import MapError

CHUNK_POINTS = 1 << 20     # points per read
FIRST_CHUNK = 1 << 17      # the first read of a LAS/LAZ: a preview of the map comes from it at once
LOD_FORMATS = ("las", "laz", "ply", "pcd")


class _Input:
    """A file as raw records: ``dtype``, ``count`` (None until read), ``chunks()``, ``positions(recs)``."""

    path: str
    dtype: np.dtype
    count: int
    bounds: tuple[np.ndarray, np.ndarray]

    def chunks(self) -> Iterator[np.ndarray]:
        raise NotImplementedError

    def positions(self, recs: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def decode(self, recs: np.ndarray) -> dict[str, np.ndarray]:
        """Records as a node's load gives them: ``positions`` (n, 3) float64 and the channels."""
        out = {"positions": self.positions(recs)}
        for name in recs.dtype.names:
            if name not in ("x", "y", "z"):
                out[name] = np.array(recs[name])
        return out

    def chunk_bounds(self, recs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.bounds  # PLY/PCD bounds come from the points themselves

    def codes(self, recs: np.ndarray, lo: np.ndarray, side: float) -> np.ndarray:
        from .kernels import morton_codes

        return morton_codes(np.ascontiguousarray(self.positions(recs)), lo, side)


def _las_error(path: str, exc: BaseException) -> MapError:
    return MapError(path, f"not a valid LAS/LAZ file ({type(exc).__name__}: {' '.join(str(exc).split())})")


class _LasInput(_Input):
    def __init__(self, path: str):
        import laspy
        from pointflow import formats

        self.path = path
        try:
            formats.las.precheck_las(path)
            with laspy.open(path, laz_backend=formats.las.laz_backend()) as f:
                formats.las.check_las_header(path, f.header)
                self.header = f.header
        except formats.FormatError as exc:
            raise MapError(path, exc.message) from None
        except BaseException as exc:
            if not formats.las.is_las_failure(exc):
                raise
            raise _las_error(path, exc) from None
        h = self.header
        self.point_format = h.point_format
        self.dtype = h.point_format.dtype()
        self.count = int(h.point_count)
        self.scales, self.offsets = np.asarray(h.scales, np.float64), np.asarray(h.offsets, np.float64)
        self.bounds = (np.asarray(h.mins, np.float64), np.asarray(h.maxs, np.float64))
        self.header_bytes = int(h.offset_to_point_data)

    def chunks(self) -> Iterator[np.ndarray]:
        import laspy
        from pointflow import formats

        try:
            with laspy.open(self.path, laz_backend=formats.las.laz_backend()) as f:
                n = FIRST_CHUNK  # small first: the map stage previews the map from it
                while True:
                    pts = f.read_points(n)
                    if not len(pts):
                        return
                    yield pts.array
                    n = CHUNK_POINTS
        except BaseException as exc:
            if not formats.las.is_las_failure(exc):
                raise
            raise _las_error(self.path, exc) from None

    def positions(self, recs: np.ndarray) -> np.ndarray:
        from .lasrec import las_positions

        return las_positions(recs, self.scales, self.offsets)

    def decode(self, recs: np.ndarray) -> dict[str, np.ndarray]:
        from .lasrec import las_points

        return las_points(np.ascontiguousarray(recs), self.point_format, self.scales, self.offsets)

    def chunk_bounds(self, recs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        lo = np.array([recs[f].min() for f in ("X", "Y", "Z")], np.float64) * self.scales + self.offsets
        hi = np.array([recs[f].max() for f in ("X", "Y", "Z")], np.float64) * self.scales + self.offsets
        return np.minimum(lo, hi), np.maximum(lo, hi)  # a negative scale swaps them

    def codes(self, recs: np.ndarray, lo: np.ndarray, side: float) -> np.ndarray:
        from .kernels import morton_codes_int

        return morton_codes_int(recs["X"], recs["Y"], recs["Z"], self.scales, self.offsets, lo, side)


def table_dtype(channels: dict[str, np.ndarray], pos_dtype=np.float64) -> np.dtype:
    fields = [("x", pos_dtype), ("y", pos_dtype), ("z", pos_dtype)]
    for k, v in channels.items():
        fields.append((k, v.dtype, v.shape[1:]) if v.ndim > 1 else (k, v.dtype))
    return np.dtype(fields)


class _TableInput(_Input):
    """PCD and ASCII PLY through the project's readers (pointflow.formats): read whole,
    then indexed in chunks. These readers hold the file in memory (LAS/LAZ and binary PLY do not)."""

    def __init__(self, path: str, fmt: str):
        from pointflow import formats

        self.path = path
        try:
            pos, ch = formats.read(path, fmt)
        except formats.FormatError as exc:
            raise MapError(path, exc.message) from None
        pos = np.asarray(pos)
        self.dtype = table_dtype(ch, pos.dtype if pos.dtype in (np.float32, np.float64) else np.float64)
        rec = np.empty(pos.shape[0], self.dtype)
        rec["x"], rec["y"], rec["z"] = pos[:, 0], pos[:, 1], pos[:, 2]
        for k, v in ch.items():
            rec[k] = v
        self._rec = rec
        self.count = int(rec.shape[0])
        finite = finite_rows(pos)
        if not finite.all():
            raise MapError(path, f"{int((~finite).sum())} points have a NaN or infinite coordinate")
        self.bounds = ((column_min(pos).astype(np.float64), column_max(pos).astype(np.float64)) if self.count
                       else (np.zeros(3), np.zeros(3)))
        self.header_bytes = 65536

    def chunks(self) -> Iterator[np.ndarray]:
        for a in range(0, self.count, CHUNK_POINTS):
            yield self._rec[a:a + CHUNK_POINTS]

    def positions(self, recs: np.ndarray) -> np.ndarray:
        return np.column_stack([recs["x"], recs["y"], recs["z"]]).astype(np.float64)


class _PlyStream(_Input):
    """A binary PLY indexed in chunks, as LAS is: memory holds a chunk, not the file. plyfile
    parses the header (its memory map gives the vertex dtype and where the data starts); the
    chunks are then plain reads, so a file cut short while indexing is an error, not a SIGBUS.
    Fields map to positions and channels exactly as the project's PLY reader maps them
    (``formats.base.split_fields``), one chunk at a time."""

    @classmethod
    def open(cls, path: str):
        """None where this cannot stream the file (no plyfile, ASCII, list properties, float
        colours whose scale depends on all values): the whole-file reader takes it then."""
        try:
            import plyfile
        except ImportError:
            return None
        from pointflow import formats

        try:
            ply = plyfile.PlyData.read(path, mmap="r")
            if ply.text or not ply.elements or ply.elements[0].name != "vertex":
                return None
            data = ply.elements[0].data
        except Exception:  # noqa: BLE001 - a malformed file: the project's reader names what is wrong
            return None
        if not isinstance(data, np.memmap) or data.dtype.names is None:
            return None
        lower = {n.lower(): n for n in data.dtype.names}
        for trio in formats.base.RGB_NAMES:
            if all(t in lower for t in trio) and any(data.dtype[lower[t]].kind == "f" for t in trio):
                return None
        dtype, offset, count = data.dtype, int(data.offset), int(data.shape[0])
        del data, ply  # no mapping is kept: see the class docstring
        return cls(path, dtype, offset, count)

    def __init__(self, path: str, file_dtype: np.dtype, offset: int, count: int):
        from pointflow import formats

        self.path, self._file_dtype, self._offset, self.count = path, file_dtype, offset, count
        self._names = file_dtype.names
        try:
            _, ch = self._fields(self._read(0, min(1, count)))
        except formats.FormatError as exc:
            raise MapError(path, exc.message) from None
        self.dtype = table_dtype(ch, np.float64)
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for a in range(0, self.count, CHUNK_POINTS):
            part = self._read(a, min(CHUNK_POINTS, self.count - a))
            pos = np.column_stack([np.asarray(part[self._lower[k]], np.float64) for k in ("x", "y", "z")])
            bad = ~finite_rows(pos)
            if bad.any():
                raise MapError(path, f"{int(bad.sum())} points have a NaN or infinite coordinate")
            lo, hi = np.minimum(lo, column_min(pos)), np.maximum(hi, column_max(pos))
        self.bounds = (lo, hi) if self.count else (np.zeros(3), np.zeros(3))
        self.header_bytes = 65536

    def _read(self, start: int, n: int) -> np.ndarray:
        part = np.fromfile(self.path, self._file_dtype, count=n, offset=self._offset + start * self._file_dtype.itemsize)
        if part.shape[0] != n:
            raise MapError(self.path, f"PLY promises {self.count} vertices, the file ends after {start + part.shape[0]}")
        return part

    @property
    def _lower(self) -> dict:
        return {n.lower(): n for n in self._names}

    def _fields(self, part: np.ndarray):
        from pointflow import formats

        return formats.base.split_fields(self.path, self._names,
                                     lambda nm: part[nm].astype(part.dtype[nm].newbyteorder("=")))

    def chunks(self) -> Iterator[np.ndarray]:
        for a in range(0, self.count, CHUNK_POINTS):
            pos, ch = self._fields(self._read(a, min(CHUNK_POINTS, self.count - a)))
            rec = np.empty(pos.shape[0], self.dtype)
            rec["x"], rec["y"], rec["z"] = pos[:, 0], pos[:, 1], pos[:, 2]
            for k, v in ch.items():
                rec[k] = v
            yield rec

    def positions(self, recs: np.ndarray) -> np.ndarray:
        return np.column_stack([recs["x"], recs["y"], recs["z"]]).astype(np.float64)


def map_format(path: str) -> str:
    ext = os.path.splitext(path)[1].lower().lstrip(".")
    if ext not in LOD_FORMATS:
        raise MapError(path, f"a map file must be COPC, LAS, LAZ, PLY or PCD; not {ext or 'a file without extension'!r}")
    return ext


def open_input(path: str) -> _Input:
    fmt = map_format(path)
    if fmt in ("las", "laz"):
        return _LasInput(path)
    if fmt == "ply":
        stream = _PlyStream.open(path)
        if stream is not None:
            return stream
    return _TableInput(path, fmt)


def file_identity(path: str, header_bytes: int) -> dict:
    """What keys an index to its file: size, mtime and a SHA-1 of the header (at most 1 MiB)."""
    st = os.stat(path)
    with open(path, "rb") as f:
        head = f.read(min(max(header_bytes, 375), 1 << 20))
    return {"size": st.st_size, "mtime_ns": st.st_mtime_ns, "header_sha1": hashlib.sha1(head).hexdigest()}


def header_bytes_of(path: str) -> int:
    """Bytes of header to checksum, read without laspy (cheap: every open checks it)."""
    if map_format(path) in ("las", "laz"):
        with open(path, "rb") as f:
            raw = f.read(100)
        if len(raw) >= 100 and raw[:4] == b"LASF":
            return struct.unpack_from("<I", raw, 96)[0]
    return 65536
