"""COPC files read through their own hierarchy (laspy's :class:`laspy.CopcReader` for the
header, the info VLR and the root hierarchy page; lazrs decompresses each node's LAZ chunk).

All hierarchy pages are read at open (they are small: 32 bytes a node) and checked against
the file: an entry whose chunk or page lies outside the file, a negative size, a page that
is not a whole number of entries, or a node whose parent is missing is a broken hierarchy
(:class:`MapError`), found before any point is drawn rather than in the middle of a flight."""
from __future__ import annotations

import os
import struct

import numpy as np

from .errors import MapError
from .lasrec import las_channel_names, las_points

_ENTRY = struct.Struct("<iiiiQii")  # VoxelKey (d, x, y, z), offset, byte size, point count


def is_copc(path: str) -> bool:
    """A LAS 1.4 file whose first VLR is the COPC info VLR ("copc", record 1)."""
    try:
        with open(path, "rb") as f:
            head = f.read(375 + 54)
    except OSError:
        return False
    if len(head) < 375 + 54 or head[:4] != b"LASF":
        return False
    hsize = struct.unpack_from("<H", head, 94)[0]
    if hsize + 54 > len(head):
        with open(path, "rb") as f:
            f.seek(hsize)
            vlr = f.read(54)
    else:
        vlr = head[hsize:hsize + 54]
    return len(vlr) == 54 and vlr[2:18].rstrip(b"\0") == b"copc" and struct.unpack_from("<H", vlr, 18)[0] == 1


def _las_failure(exc: BaseException) -> bool:
    from pointflow.formats.las import is_las_failure as _is_las_failure

    return _is_las_failure(exc)


class CopcFile:
    """One COPC file: its octree nodes (keys (d, x, y, z) as in the COPC specification)."""

    kind = "copc"

    def __init__(self, path: str):
        from laspy import CopcReader

        self.path = path
        self.size = os.path.getsize(path)
        try:
            from pointflow.formats.las import precheck_las as _precheck_las

            _precheck_las(path)
        except ValueError as exc:
            raise MapError(path, getattr(exc, "message", str(exc))) from None
        try:
            reader = CopcReader.open(path)
        except BaseException as exc:
            if not _las_failure(exc):
                raise
            raise MapError(path, f"not a valid COPC file ({type(exc).__name__}: {' '.join(str(exc).split())})") from None
        try:
            self._init(reader)
        except BaseException:
            reader.source.close()
            raise

    def _init(self, reader) -> None:
        h, info = reader.header, reader.copc_info
        self._reader = reader
        self._f = reader.source
        self.header = h
        self.point_format = h.point_format
        self.scales, self.offsets = np.asarray(h.scales, np.float64), np.asarray(h.offsets, np.float64)
        self._laszip = reader.laszip_vlr.record_data
        self.point_count = int(h.point_count)
        if not (np.all(np.isfinite(info.center)) and np.isfinite(info.halfsize) and info.halfsize > 0):
            raise MapError(self.path, f"broken COPC info (center {list(info.center)}, halfsize {info.halfsize})")
        self.cube_lo = np.asarray(info.center, np.float64) - info.halfsize
        self.cube_side = 2.0 * float(info.halfsize)
        self.root_spacing = float(info.spacing) if info.spacing > 0 else self.cube_side / 128
        self.bounds = (np.asarray(h.mins, np.float64), np.asarray(h.maxs, np.float64))
        self.channels = las_channel_names(self.point_format)
        self.nodes = self._read_hierarchy(info.hierarchy_root_offset, info.hierarchy_root_size)
        total = sum(n[2] for n in self.nodes.values())
        if total != self.point_count:
            raise MapError(self.path, f"broken COPC hierarchy: its nodes hold {total} points, the header says "
                                      f"{self.point_count}")

    def _read_hierarchy(self, offset: int, size: int) -> dict:
        """Every page, breadth first; entries with points become nodes {key: (offset, bytes, count)}."""
        nodes: dict[tuple, tuple[int, int, int]] = {}
        pages = [(offset, size, "the root hierarchy page")]
        seen = set()
        while pages:
            off, nbytes, what = pages.pop()
            if (off, nbytes) in seen:
                raise MapError(self.path, f"broken COPC hierarchy: {what} at byte {off} is referenced twice")
            seen.add((off, nbytes))
            if nbytes < 0 or nbytes % _ENTRY.size or off < 375 or off + nbytes > self.size:
                raise MapError(self.path, f"broken COPC hierarchy: {what} ({nbytes} bytes at byte {off}) does not fit "
                                          f"a file of {self.size} bytes in whole 32-byte entries")
            self._f.seek(off)
            raw = self._f.read(nbytes)
            if len(raw) != nbytes:
                raise MapError(self.path, f"broken COPC hierarchy: {what} is cut short")
            for d, x, y, z, eoff, esize, count in _ENTRY.iter_unpack(raw):
                key = (d, x, y, z)
                if d < 0 or d > 30 or min(x, y, z) < 0 or max(x, y, z) >= (1 << d):
                    raise MapError(self.path, f"broken COPC hierarchy: entry key {key} is not an octree key")
                if count == -1:
                    pages.append((eoff, esize, f"the hierarchy page of {key}"))
                elif count > 0:
                    if esize <= 0 or eoff < 375 or eoff + esize > self.size:
                        raise MapError(self.path, f"broken COPC hierarchy: node {key} has its {esize} bytes at byte "
                                                  f"{eoff}, outside a file of {self.size} bytes")
                    nodes[key] = (eoff, esize, count)
                elif count < -1:
                    raise MapError(self.path, f"broken COPC hierarchy: node {key} has {count} points")
        if (0, 0, 0, 0) not in nodes and nodes:
            raise MapError(self.path, "broken COPC hierarchy: no root node (0, 0, 0, 0)")
        return nodes

    def load(self, key: tuple) -> dict[str, np.ndarray]:
        import lazrs
        from laspy import PackedPointRecord

        try:
            off, nbytes, count = self.nodes[key]
        except KeyError:
            raise KeyError(f"{self.path}: no node {key}") from None
        comp = os.pread(self._f.fileno(), nbytes, off)  # no shared file position: loads run in threads
        if len(comp) != nbytes:
            raise MapError(self.path, f"node {key}: {nbytes} bytes at byte {off} are cut short (truncated file?)")
        raw = np.zeros(count * self.point_format.size, np.uint8)
        try:
            lazrs.decompress_points_with_chunk_table(comp, self._laszip, raw, [(count, nbytes)],
                                                     self._reader.decompression_selection)
        except BaseException as exc:
            if not _las_failure(exc):
                raise
            raise MapError(self.path, f"node {key}: its LAZ chunk does not decompress "
                                      f"({type(exc).__name__}: {' '.join(str(exc).split())})") from None
        rec = PackedPointRecord.from_buffer(raw, self.point_format)
        return las_points(rec.array, self.point_format, self.scales, self.offsets)

    @property
    def bytes_per_point(self) -> int:
        """Bytes a decoded point takes: positions (3 float64) and each channel."""
        from .lasrec import LAS_CHANNEL_BYTES

        return 24 + sum(LAS_CHANNEL_BYTES[c] for c in self.channels)

    def spacing(self, depth: int) -> float:
        return self.root_spacing / (1 << depth)

    def close(self) -> None:
        try:
            self._f.close()
        except OSError:
            pass
