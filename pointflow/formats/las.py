"""LAS/LAZ (laspy; lazrs single-threaded): headers checked against the file before laspy
trusts them, records to positions and channels, pieces of bounded size."""
from __future__ import annotations

import os
import struct
from typing import Iterator

import numpy as np

from .base import FormatError

#: read_las reads LAS/LAZ in pieces of at most this many points.
LAS_PIECE_POINTS = 1 << 20


def las_failures() -> tuple[type[BaseException], ...]:
    """What laspy (and its LAZ backend) raise on a malformed file, besides OSError/ValueError."""
    import laspy

    try:
        from lazrs import LazrsError
    except ImportError:  # pragma: no cover - LAZ through another backend
        LazrsError = laspy.LaspyException
    return (laspy.LaspyException, LazrsError, struct.error, OSError, ValueError, KeyError, IndexError, EOFError, MemoryError,
            OverflowError, TypeError, AttributeError)


def laz_backend():
    """lazrs single-threaded: its parallel decompressor sizes buffers from the chunk table's
    byte counts, so a corrupt table aborts the process on a failed allocation."""
    import laspy

    return laspy.LazBackend.Lazrs if laspy.LazBackend.Lazrs.is_available() else None


def is_las_failure(exc: BaseException) -> bool:
    # a Rust panic in lazrs arrives as pyo3's PanicException, a BaseException
    return isinstance(exc, las_failures()) or type(exc).__name__ == "PanicException"


def las_error(path: str, exc: BaseException) -> FormatError:
    return FormatError(path, f"not a valid LAS/LAZ file ({type(exc).__name__}: {' '.join(str(exc).split())})")


def las_record_channels(pts, dims: set, copy: bool = False) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Positions (float64, laspy's own scaling) and the channels pointflow keeps of laspy
    points (intensity, classification, return_number, gps_time and rgb when the format has
    them). ``copy``: channels own their memory instead of viewing the records (a cache that
    counts bytes must not keep a whole record array alive through one channel)."""
    arr = np.array if copy else np.asarray
    pos = np.column_stack([np.asarray(pts.x, np.float64), np.asarray(pts.y, np.float64),
                           np.asarray(pts.z, np.float64)])
    ch: dict[str, np.ndarray] = {"intensity": arr(pts.intensity, np.uint16),
                                 "classification": arr(pts.classification, np.uint8),
                                 "return_number": arr(pts.return_number, np.uint8)}
    if "gps_time" in dims:
        ch["gps_time"] = arr(pts.gps_time, np.float64)
    if {"red", "green", "blue"} <= dims:
        ch["rgb"] = np.column_stack([np.asarray(pts.red), np.asarray(pts.green),
                                     np.asarray(pts.blue)]).astype(np.uint16)
    return pos, ch


def iter_las(path: str, chunk_points: int) -> Iterator[tuple[np.ndarray, dict]]:
    """LAS/LAZ in pieces of ``chunk_points`` (laspy's chunk iterator: big files stream).
    A malformed file (header or points) raises :class:`FormatError`, never laspy's own errors."""
    import laspy

    precheck_las(path)
    try:
        with laspy.open(path, laz_backend=laz_backend()) as f:
            check_las_header(path, f.header)
            dims = set(f.header.point_format.dimension_names)
            for pts in f.chunk_iterator(chunk_points):
                yield las_record_channels(pts, dims)
    except FormatError:
        raise
    except BaseException as exc:
        raise las_error(path, exc) if is_las_failure(exc) else exc from None


def check_las_header(path: str, h) -> None:
    """Header values laspy accepts but that cannot describe points."""
    scales, offsets = np.asarray(h.scales, np.float64), np.asarray(h.offsets, np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        span = np.abs(scales) * 2.0 ** 31 + np.abs(offsets)  # the largest coordinate a record can give
    if not (np.all(np.isfinite(span)) and np.all(span < 1e300) and np.all(scales != 0)):
        raise FormatError(path, f"not a valid LAS/LAZ file (scales {list(h.scales)}, offsets {list(h.offsets)})")


def precheck_las(path: str) -> None:
    """Check the public header block's sizes and counts against the file before laspy reads
    it: laspy trusts them (a VLR count of 2^32 loops for minutes, a point count of 2^32
    allocates hundreds of GB). Offsets as in the LAS 1.0-1.4 specifications."""
    size = os.path.getsize(path)

    def bad(what: str) -> FormatError:
        return FormatError(path, f"not a valid LAS/LAZ file ({what})")

    with open(path, "rb") as f:
        raw = f.read(375)
    if len(raw) < 227:
        raise bad(f"truncated header: {len(raw)} bytes, a LAS header has at least 227")
    if raw[:4] != b"LASF":
        raise bad(f"no 'LASF' signature at the start, found {raw[:4]!r}")
    major, minor = raw[24], raw[25]
    if major != 1 or minor > 4:
        raise bad(f"version {major}.{minor}, expected 1.0 to 1.4")
    hsize, offset, nvlr = struct.unpack_from("<HII", raw, 94)
    fmt_id, reclen, legacy = struct.unpack_from("<BHI", raw, 104)
    if not 227 <= hsize <= offset <= size:
        raise bad(f"header size {hsize} and point data offset {offset} do not fit a file of {size} bytes")
    if nvlr * 54 > offset - hsize:
        raise bad(f"{nvlr} VLRs do not fit in the {offset - hsize} bytes between header and points")
    if (fmt_id & 0x3F) > 10 or reclen == 0:
        raise bad(f"point format {fmt_id & 0x3F} with {reclen}-byte records")
    count = legacy
    if minor >= 4:
        if hsize < 375 or len(raw) < 375:
            raise bad(f"a LAS 1.4 header has 375 bytes, this one {min(hsize, len(raw))}")
        evlr_start, n_evlr, count = struct.unpack_from("<QIQ", raw, 235)
        count = count or legacy
        if n_evlr and (evlr_start > size or n_evlr * 60 > size - evlr_start):
            raise bad(f"{n_evlr} extended VLRs at byte {evlr_start} do not fit a file of {size} bytes")
    compressed = bool(fmt_id & 0xC0)
    if not compressed and count * reclen > size - offset:
        raise bad(f"header promises {count} points of {reclen} bytes, the file has {size - offset} bytes of points")
    if compressed:
        precheck_laz_chunks(path, size, hsize, nvlr, offset, reclen, bad)


def precheck_laz_chunks(path: str, size: int, hsize: int, nvlr: int, offset: int, reclen: int, bad) -> None:
    """LAZ: the chunk table's place and length fit the file (lazrs allocates the table from
    its count before reading it, and a failed allocation aborts the process). Every chunk
    starts with one raw point, so there are at most (compressed bytes / record length) chunks."""
    with open(path, "rb") as f:
        f.seek(hsize)
        vlrs = f.read(offset - hsize)
        pos, found = 0, False
        for _ in range(nvlr):
            if pos + 54 > len(vlrs):
                raise bad("VLR headers run past the point data")
            user, rec_id, length = vlrs[pos + 2:pos + 18], *struct.unpack_from("<HH", vlrs, pos + 18)
            found = found or (user.rstrip(b"\0") == b"laszip encoded" and rec_id == 22204)
            pos += 54 + length
        if pos > len(vlrs):
            raise bad("VLRs run past the point data")
        if not found:
            raise bad("compressed points but no laszip VLR")
        f.seek(offset)
        head = f.read(8)
        if len(head) < 8:
            raise bad("compressed point data is missing")
        table = struct.unpack("<q", head)[0]
        if table == -1:  # written while streaming: the offset is in the last 8 bytes
            f.seek(size - 8)
            table = struct.unpack("<q", f.read(8))[0]
        if not offset + 8 <= table <= size - 8:
            raise bad(f"LAZ chunk table at byte {table} lies outside the point data (bytes {offset + 8} to {size - 8})")
        f.seek(table)
        _version, n_chunks = struct.unpack("<II", f.read(8))
        if n_chunks > max(1, (table - offset - 8) // reclen):
            raise bad(f"LAZ chunk table lists {n_chunks} chunks, {table - offset - 8} compressed bytes hold at most "
                      f"{max(1, (table - offset - 8) // reclen)}")


def las_point_count(path: str) -> int:
    import laspy

    precheck_las(path)
    try:
        with laspy.open(path, laz_backend=laz_backend()) as f:
            check_las_header(path, f.header)
            return int(f.header.point_count)
    except FormatError:
        raise
    except BaseException as exc:
        raise las_error(path, exc) if is_las_failure(exc) else exc from None


def read_las(path: str, columns=None) -> tuple[np.ndarray, dict]:
    """A whole LAS/LAZ file, read in pieces of bounded size: a LAZ header's point count cannot
    be checked against the file size, and one piece of that many points would be allocated
    up front."""
    pieces = list(iter_las(path, LAS_PIECE_POINTS))
    if not pieces:
        return np.zeros((0, 3)), {}
    if len(pieces) == 1:
        return pieces[0]
    return (np.concatenate([p for p, _ in pieces]),
            {k: np.concatenate([c[k] for _, c in pieces]) for k in pieces[0][1]})


#: EPSG linear units as the views label them (GeoTIFF's ProjLinearUnitsGeoKey and friends).
_EPSG_UNITS = {9001: "m", 9002: "ft", 9003: "US ft", 9036: "km", 9030: "nmi", 9005: "Clarke ft", 9014: "fathom"}
_UNIT_NAMES = {"metre": "m", "meter": "m", "foot": "ft", "us survey foot": "US ft", "kilometre": "km",
               "foot_us": "US ft", "us_survey_foot": "US ft"}


def crs_units(header) -> "dict[str, str] | None":
    """The length units of a LAS header's coordinates, ``{"xy": "ft", "z": "ft"}``, from its
    CRS (the WKT VLR or the GeoTIFF keys, read by laspy and pyproj), so a view labels a map
    in feet as feet; None when the file does not say, or says angles (a geographic CRS).
    ``z`` is the vertical CRS's unit where there is one, else the horizontal one's."""
    xy = z = None
    try:
        crs = header.parse_crs()
    except Exception:  # noqa: BLE001 - no pyproj, or a CRS pyproj does not read: the keys below
        crs = None
    if crs is not None:
        axes = crs.axis_info
        if crs.is_projected or crs.is_compound:
            horiz = [a for a in axes if a.direction.lower() in ("east", "north", "west", "south")]
            up = [a for a in axes if a.direction.lower() in ("up", "down")]
            xy = _unit_label(horiz[0]) if horiz and not _angular(horiz[0]) else None
            z = _unit_label(up[0]) if up else None
    if xy is None:  # no WKT pyproj reads: the GeoTIFF keys' own unit codes
        keys = {}
        for vlr in getattr(header, "vlrs", ()):
            for k in getattr(vlr, "geo_keys", ()) or ():
                keys[int(k.id)] = int(k.value_offset)
        xy = _EPSG_UNITS.get(keys.get(3076, -1))  # ProjLinearUnitsGeoKey
        z = z or _EPSG_UNITS.get(keys.get(4099, -1))  # VerticalUnitsGeoKey
    if xy is None:
        return None
    return {"xy": xy, "z": z or xy}


def _angular(axis) -> bool:
    return "degree" in axis.unit_name.lower() or "radian" in axis.unit_name.lower() or "grad" in axis.unit_name.lower()


def _unit_label(axis) -> str:
    code = axis.unit_code
    if code and str(code).isdigit() and int(code) in _EPSG_UNITS:
        return _EPSG_UNITS[int(code)]
    return _UNIT_NAMES.get(axis.unit_name.lower(), axis.unit_name)
