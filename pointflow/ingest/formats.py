"""Point-cloud file readers (and small writers) for the ``file`` transport.

Every reader returns ``(positions, channels)``: positions (N, 3) float64 (float32 where
the format stores float32: KITTI, Ouster npz) and a dict of per-point channels in the
file's own dtypes; ``rgb`` is (N, 3). Readers are vectorised (numpy structured dtypes,
``np.loadtxt``); a malformed file raises :class:`FormatError` naming the file and what
is wrong.

Formats: LAS/LAZ (laspy; intensity, classification, gps_time, rgb, return_number), PLY
(ascii, binary little/big endian), PCD (ascii, binary, binary_compressed via python-lzf), NPY ((N,>=3) array or structured
x/y/z), NPZ (``xyz``/``points``/``positions`` or x/y/z arrays + per-point arrays, e.g.
Ouster ``range``, ``reflectivity``), CSV/XYZ/TXT (header row optional), KITTI ``.bin``
(float32 x, y, z, reflectance -> ``intensity``).
"""
from __future__ import annotations

import os
import struct
import tokenize
import warnings
import zipfile
from typing import Iterator, Sequence

from ..errors import KeyedError

import numpy as np

#: read_points reads LAS/LAZ in pieces of at most this many points.
LAS_PIECE_POINTS = 1 << 20

FORMATS = ("las", "laz", "ply", "pcd", "npy", "npz", "csv", "xyz", "txt", "bin")


class FormatError(KeyedError):
    """A point file that cannot be read; ``key`` (also ``path``) is the file."""

    @property
    def path(self) -> str:
        return self.key


def detect_format(path: str) -> str:
    ext = os.path.splitext(path)[1].lower().lstrip(".")
    if ext not in FORMATS:
        raise FormatError(path, f"unknown point-cloud format {ext!r}; expected one of {', '.join(FORMATS)} (or set 'format')")
    return ext


#: What numpy, zipfile and the header parsers raise on a corrupt file (zipfile: a damaged or
#: encrypted archive; tokenize/SyntaxError: an .npy header dict that does not parse;
#: MemoryError: a count the size checks let through).
_READ_FAILURES = (OSError, ValueError, KeyError, IndexError, EOFError, zipfile.BadZipFile, NotImplementedError,
                  tokenize.TokenError, SyntaxError, struct.error, MemoryError, OverflowError)


def _check_npy_header(path: str, f, nbytes: int, member: str = "") -> None:
    """The .npy header's shape and dtype must fit the ``nbytes`` that hold it (numpy
    allocates the whole array from the header before reading)."""
    where = f"member {member}: " if member else ""
    major, _ = np.lib.format.read_magic(f)
    read_header = np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "Reading `.npy` or `.npz` file required additional header parsing")
        shape, _, dtype = read_header(f)
    if dtype.hasobject:
        raise FormatError(path, f"{where}holds Python objects, not numbers")
    count = int(np.prod(shape, dtype=object)) if shape else 1
    if count * dtype.itemsize > nbytes - f.tell():
        raise FormatError(path, f"{where}array header says shape {shape} of {dtype}, only {nbytes - f.tell()} "
                                "bytes follow")


def read_points(path: str, fmt: str | None = None, columns: Sequence[str] | None = None):
    """Read a whole file."""
    fmt = (fmt or detect_format(path)).lower()
    try:
        if fmt in ("las", "laz"):
            # pieces of bounded size: a LAZ header's point count cannot be checked against the
            # file size, and one piece of that many points would be allocated up front
            pieces = list(iter_las(path, LAS_PIECE_POINTS))
            if not pieces:
                return np.zeros((0, 3)), {}
            if len(pieces) == 1:
                return pieces[0]
            return (np.concatenate([p for p, _ in pieces]),
                    {k: np.concatenate([c[k] for _, c in pieces]) for k in pieces[0][1]})
        if fmt == "ply":
            return read_ply(path)
        if fmt == "pcd":
            return read_pcd(path)
        if fmt == "npy":
            with open(path, "rb") as f:
                _check_npy_header(path, f, os.fstat(f.fileno()).st_size)
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", "Reading `.npy` or `.npz` file required additional header parsing")
                return _from_array(path, np.load(path, allow_pickle=False))
        if fmt == "npz":
            return read_npz(path)
        if fmt in ("csv", "xyz", "txt"):
            return read_text(path, columns)
        if fmt == "bin":
            return read_kitti(path)
    except FormatError:
        raise
    except _READ_FAILURES as exc:
        raise FormatError(path, f"cannot read as {fmt}: {type(exc).__name__}: {' '.join(str(exc).split())}") from None
    raise FormatError(path, f"unsupported format {fmt!r}")


# --------------------------------------------------------------------------- LAS / LAZ
def _las_failures() -> tuple[type[BaseException], ...]:
    """What laspy (and its LAZ backend) raise on a malformed file, besides OSError/ValueError."""
    import laspy

    try:
        from lazrs import LazrsError
    except ImportError:  # pragma: no cover - LAZ through another backend
        LazrsError = laspy.LaspyException
    return (laspy.LaspyException, LazrsError, struct.error, OSError, ValueError, KeyError, IndexError, EOFError, MemoryError,
            OverflowError, TypeError, AttributeError)


def _laz_backend():
    """lazrs single-threaded: its parallel decompressor sizes buffers from the chunk table's
    byte counts, so a corrupt table aborts the process on a failed allocation."""
    import laspy

    return laspy.LazBackend.Lazrs if laspy.LazBackend.Lazrs.is_available() else None


def _is_las_failure(exc: BaseException) -> bool:
    # a Rust panic in lazrs arrives as pyo3's PanicException, a BaseException
    return isinstance(exc, _las_failures()) or type(exc).__name__ == "PanicException"


def _las_error(path: str, exc: BaseException) -> FormatError:
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

    _precheck_las(path)
    try:
        with laspy.open(path, laz_backend=_laz_backend()) as f:
            _check_las_header(path, f.header)
            dims = set(f.header.point_format.dimension_names)
            for pts in f.chunk_iterator(chunk_points):
                yield las_record_channels(pts, dims)
    except FormatError:
        raise
    except BaseException as exc:
        raise _las_error(path, exc) if _is_las_failure(exc) else exc from None


def _check_las_header(path: str, h) -> None:
    """Header values laspy accepts but that cannot describe points."""
    scales, offsets = np.asarray(h.scales, np.float64), np.asarray(h.offsets, np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        span = np.abs(scales) * 2.0 ** 31 + np.abs(offsets)  # the largest coordinate a record can give
    if not (np.all(np.isfinite(span)) and np.all(span < 1e300) and np.all(scales != 0)):
        raise FormatError(path, f"not a valid LAS/LAZ file (scales {list(h.scales)}, offsets {list(h.offsets)})")


def _precheck_las(path: str) -> None:
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
        _precheck_laz_chunks(path, size, hsize, nvlr, offset, reclen, bad)


def _precheck_laz_chunks(path: str, size: int, hsize: int, nvlr: int, offset: int, reclen: int, bad) -> None:
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

    _precheck_las(path)
    try:
        with laspy.open(path, laz_backend=_laz_backend()) as f:
            _check_las_header(path, f.header)
            return int(f.header.point_count)
    except FormatError:
        raise
    except BaseException as exc:
        raise _las_error(path, exc) if _is_las_failure(exc) else exc from None


# --------------------------------------------------------------------------- helpers
_RGB_NAMES = (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue"))


def _split_fields(path: str, names: Sequence[str], get) -> tuple[np.ndarray, dict]:
    """positions from x/y/z fields, rgb from red/green/blue, the rest as channels."""
    lower = {n.lower(): n for n in names}
    if not all(k in lower for k in ("x", "y", "z")):
        raise FormatError(path, f"no x, y, z fields (fields: {', '.join(names)})")
    pos = np.column_stack([np.asarray(get(lower[k]), np.float64) for k in ("x", "y", "z")])
    used = {lower["x"], lower["y"], lower["z"]}
    ch: dict[str, np.ndarray] = {}
    for trio in _RGB_NAMES:
        if all(t in lower for t in trio):
            cols = [np.asarray(get(lower[t])) for t in trio]
            dt = np.uint16 if any(c.dtype.itemsize > 1 and c.dtype.kind in "ui" for c in cols) else np.uint8
            if any(c.dtype.kind == "f" for c in cols):
                arr = np.column_stack(cols).astype(np.float32)
                ch["rgb"] = np.clip(np.rint(arr * (255 if arr.size and arr.max() <= 1 else 1)), 0, 255).astype(np.uint8)
            else:
                ch["rgb"] = np.column_stack(cols).astype(dt)
            used.update(lower[t] for t in trio)
            break
    for n in names:
        if n not in used:
            a = np.asarray(get(n))
            if a.dtype.kind in "uif":
                ch[n] = np.ascontiguousarray(a)
    return pos, ch


def _from_array(path: str, arr: np.ndarray) -> tuple[np.ndarray, dict]:
    if arr.dtype.names:
        return _split_fields(path, arr.dtype.names, lambda n: arr[n])
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise FormatError(path, f"expected an (N, >=3) array, got shape {arr.shape}")
    pos = np.ascontiguousarray(arr[:, :3])
    if pos.dtype not in (np.float32, np.float64):
        pos = pos.astype(np.float64)
    ch = {}
    with np.errstate(over="ignore", invalid="ignore"):  # beyond float32: inf, as a float32 file holds it
        if arr.shape[1] >= 4:
            ch["intensity"] = np.ascontiguousarray(arr[:, 3]).astype(np.float32)
        for j in range(4, arr.shape[1]):
            ch[f"col{j}"] = np.ascontiguousarray(arr[:, j]).astype(np.float32)
    return pos, ch


# --------------------------------------------------------------------------- NPZ / KITTI
def read_npz(path: str) -> tuple[np.ndarray, dict]:
    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            if info.filename.endswith(".npy"):
                # a member can expand at most ~1032x by deflate; its header must fit that
                limit = info.compress_size * (1 if info.compress_type == zipfile.ZIP_STORED else 1032)
                with zf.open(info) as f:
                    _check_npy_header(path, f, min(info.file_size, limit), info.filename)
    with np.load(path, allow_pickle=False) as z, warnings.catch_warnings():
        warnings.filterwarnings("ignore", "Reading `.npy` or `.npz` file required additional header parsing")
        keys = list(z.keys())
        data = {k: z[k] for k in keys}
    for k in ("xyz", "points", "positions"):
        if k in data:
            a = data.pop(k)
            if a.ndim == 3 and a.shape[-1] == 3:  # Ouster (H, W, 3) layout
                a = a.reshape(-1, 3)
                data = {n: v.reshape(-1) if v.ndim == 2 and v.size == a.shape[0] else v for n, v in data.items()}
            if a.ndim != 2 or a.shape[1] < 3:
                raise FormatError(path, f"array {k!r} must be (N, 3), got {a.shape}")
            pos = np.ascontiguousarray(a[:, :3])
            break
    else:
        if not all(k in data for k in ("x", "y", "z")):
            raise FormatError(path, f"npz needs 'xyz' (or 'points'/'positions') or 'x','y','z' arrays; has {', '.join(keys)}")
        pos = np.column_stack([data.pop(k).reshape(-1) for k in ("x", "y", "z")])
    if pos.dtype not in (np.float32, np.float64):
        pos = pos.astype(np.float64)
    n = pos.shape[0]
    ch = {}
    for k, v in data.items():
        if v.shape[:1] == (n,) and v.dtype.kind in "uif" and v.ndim in (1, 2):
            ch[k] = np.ascontiguousarray(v)  # per-point (Ouster: range, reflectivity, near_ir, flags)
    return pos, ch


def read_kitti(path: str) -> tuple[np.ndarray, dict]:
    size = os.path.getsize(path)  # np.fromfile drops a partial float: check the bytes on disk
    if size % 16:
        raise FormatError(path, f"KITTI .bin size {size} bytes is not a multiple of 16 (x, y, z, reflectance)")
    raw = np.fromfile(path, dtype="<f4")
    a = raw.reshape(-1, 4)
    return np.ascontiguousarray(a[:, :3]), {"intensity": np.ascontiguousarray(a[:, 3])}


# --------------------------------------------------------------------------- CSV / XYZ
def read_text(path: str, columns: Sequence[str] | None = None) -> tuple[np.ndarray, dict]:
    with open(path, "r", encoding="utf-8", errors="replace") as f:
        first = f.readline()
    delim = "," if "," in first else (";" if ";" in first else None)
    toks = [t.strip() for t in (first.split(delim) if delim else first.split())]
    skip = 0
    names = list(columns) if columns else None
    try:
        [float(t) for t in toks if t]
    except ValueError:
        skip = 1
        if names is None:
            names = [t.strip().strip('"').lower() for t in toks]
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "loadtxt: input contained no data")
        arr = np.loadtxt(path, delimiter=delim, skiprows=skip, ndmin=2, comments="#")
    if arr.shape[1] < 3:
        raise FormatError(path, f"text file has {arr.shape[1]} column(s); need at least x, y, z")
    if names is None:
        names = ["x", "y", "z", "intensity"][:arr.shape[1]] + [f"col{j}" for j in range(4, arr.shape[1])]
    if len(names) != arr.shape[1]:
        raise FormatError(path, f"{len(names)} column names for {arr.shape[1]} columns")
    idx = {n: j for j, n in enumerate(names)}
    pos, ch = _split_fields(path, names, lambda n: arr[:, idx[n]])
    with np.errstate(over="ignore"):  # a value beyond float32 becomes inf, as a float32 file would hold it
        return pos, {k: (v.astype(np.float32) if v.dtype == np.float64 else v) for k, v in ch.items()}


# --------------------------------------------------------------------------- header counts
def _check_count(path: str, f, n: int, values: int, what: str, unit: str) -> None:
    """A header's element count must fit the bytes after the header (checked before numpy
    allocates that many rows): at least one byte per binary value, two (a digit and a
    separator) per ascii value."""
    left = os.fstat(f.fileno()).st_size - f.tell()
    if n < 0 or n * max(values, 1) > left:
        raise FormatError(path, f"{what} header promises {n} {unit} of {values} values, "
                                f"only {left} bytes follow the header")


def _loadtxt(f, n: int, values: int) -> np.ndarray:
    """Up to n rows of numbers (an empty body gives 0 rows, not numpy's warning)."""
    if not n:
        return np.zeros((0, values))
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "loadtxt: input contained no data")
        return np.loadtxt(f, max_rows=n, ndmin=2)


# --------------------------------------------------------------------------- PLY
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def read_ply(path: str) -> tuple[np.ndarray, dict]:
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise FormatError(path, "not a PLY file (no 'ply' magic)")
        fmt = None
        elements: list[tuple[str, int, list[tuple[str, str]]]] = []
        while True:
            line = f.readline()
            if not line:
                raise FormatError(path, "PLY header has no end_header")
            t = line.decode("ascii", "replace").split()
            if not t or t[0] in ("comment", "obj_info"):
                continue
            if t[0] == "format":
                fmt = t[1]
            elif t[0] == "element":
                elements.append((t[1], int(t[2]), []))
            elif t[0] == "property":
                if t[1] == "list":
                    if elements and elements[-1][0] == "vertex":
                        raise FormatError(path, "list properties on vertices are not supported")
                    elements[-1][2].append((t[-1], "list"))
                else:
                    if t[1] not in _PLY_TYPES:
                        raise FormatError(path, f"unknown PLY property type {t[1]!r}")
                    elements[-1][2].append((t[2], _PLY_TYPES[t[1]]))
            elif t[0] == "end_header":
                break
        if not elements or elements[0][0] != "vertex":
            raise FormatError(path, "PLY has no leading 'vertex' element")
        _, n, props = elements[0]
        _check_count(path, f, n, len(props), "PLY", "vertices")
        if fmt == "ascii":
            arr = _loadtxt(f, n, len(props))
            if arr.shape[0] != n:
                raise FormatError(path, f"PLY promises {n} vertices, file has {arr.shape[0]}")
            names = [p[0] for p in props]
            return _split_fields(path, names, lambda nm: arr[:, names.index(nm)].astype(np.dtype(dict(props)[nm])))
        if fmt not in ("binary_little_endian", "binary_big_endian"):
            raise FormatError(path, f"unknown PLY format {fmt!r}")
        end = "<" if fmt == "binary_little_endian" else ">"
        dt = np.dtype([(name, end + t) for name, t in props])
        buf = f.read(n * dt.itemsize)
        if len(buf) < n * dt.itemsize:
            raise FormatError(path, f"PLY promises {n} vertices ({n * dt.itemsize} bytes), file has {len(buf)}")
        rec = np.frombuffer(buf, dtype=dt)
        return _split_fields(path, dt.names, lambda nm: rec[nm].astype(rec[nm].dtype.newbyteorder("=")))


def write_ply(path: str, positions: np.ndarray, channels: dict[str, np.ndarray] | None = None,
              binary: bool = True) -> None:
    """Write vertices (x, y, z as double, 1-D channels with their dtype, rgb as uchar)."""
    channels = channels or {}
    rev = {v: k for k, v in _PLY_TYPES.items() if k in ("char", "uchar", "short", "ushort", "int", "uint", "float", "double")}
    fields = [("x", "f8"), ("y", "f8"), ("z", "f8")]
    cols = [positions[:, 0], positions[:, 1], positions[:, 2]]
    for k, v in channels.items():
        if k == "rgb":
            for j, c in enumerate(("red", "green", "blue")):
                fields.append((c, "u1")); cols.append(v[:, j])
        else:
            fields.append((k, v.dtype.str[1:])); cols.append(v)
    n = positions.shape[0]
    head = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0", f"element vertex {n}"]
    head += [f"property {rev[t]} {nm}" for nm, t in fields] + ["end_header"]
    rec = np.empty(n, dtype=[(nm, "<" + t) for nm, t in fields])
    for (nm, _), c in zip(fields, cols):
        rec[nm] = c
    with open(path, "wb") as f:
        f.write(("\n".join(head) + "\n").encode())
        if binary:
            f.write(rec.tobytes())
        else:
            np.savetxt(f, np.column_stack([np.asarray(c, np.float64) for c in cols]), fmt="%.17g")


# --------------------------------------------------------------------------- PCD
def read_pcd(path: str) -> tuple[np.ndarray, dict]:
    meta: dict[str, list[str]] = {}
    with open(path, "rb") as f:
        while True:
            line = f.readline()
            if not line:
                raise FormatError(path, "PCD header has no DATA line")
            t = line.decode("ascii", "replace").split()
            if not t or t[0].startswith("#"):
                continue
            meta[t[0].upper()] = t[1:]
            if t[0].upper() == "DATA":
                break
        try:
            names = meta["FIELDS"]
            sizes = [int(s) for s in meta["SIZE"]]
            types = meta["TYPE"]
            counts = [int(c) for c in meta.get("COUNT", ["1"] * len(names))]
            n = int(meta.get("POINTS", [0])[0]) or int(meta["WIDTH"][0]) * int(meta.get("HEIGHT", ["1"])[0])
        except (KeyError, ValueError, IndexError) as exc:
            raise FormatError(path, f"bad PCD header: {exc}") from None
        kinds = {"F": "f", "U": "u", "I": "i"}
        cols = []
        for nm, sz, ty, ct in zip(names, sizes, types, counts):
            if ty not in kinds:
                raise FormatError(path, f"bad PCD TYPE {ty!r}")
            if sz not in ((4, 8) if ty == "F" else (1, 2, 4, 8)) or ct < 1:
                raise FormatError(path, f"bad PCD field {nm!r}: SIZE {sz}, TYPE {ty}, COUNT {ct}")
            dt = np.dtype(f"<{kinds[ty]}{sz}")
            cols.append((nm if nm != "_" else f"_pad{len(cols)}", dt, ct))
        mode = meta["DATA"][0].lower() if meta["DATA"] else ""
        if mode in ("ascii", "binary"):  # uncompressed: the count must fit the bytes that follow
            _check_count(path, f, n, sum(c[2] for c in cols), "PCD", "points")
        if mode == "ascii":
            arr = _loadtxt(f, n, sum(c[2] for c in cols))
            if arr.shape[0] != n:
                raise FormatError(path, f"PCD promises {n} points, file has {arr.shape[0]}")
            rec = np.empty(n, dtype=[(nm, dt, (ct,)) if ct > 1 else (nm, dt) for nm, dt, ct in cols])
            j = 0
            for nm, dt, ct in cols:
                rec[nm] = arr[:, j:j + ct].astype(dt) if ct > 1 else arr[:, j].astype(dt)
                j += ct
        elif mode == "binary":
            dt = np.dtype([(nm, dt, (ct,)) if ct > 1 else (nm, dt) for nm, dt, ct in cols])
            buf = f.read(n * dt.itemsize)
            if len(buf) < n * dt.itemsize:
                raise FormatError(path, f"PCD promises {n} points ({n * dt.itemsize} bytes), file has {len(buf)}")
            rec = np.frombuffer(buf, dtype=dt)
        elif mode == "binary_compressed":
            rec = _pcd_lzf(path, f, n, cols)
        else:
            raise FormatError(path, f"PCD DATA {mode!r} is not supported (ascii, binary, binary_compressed)")
    fields = [c[0] for c in cols if not c[0].startswith("_pad") and c[2] == 1]

    def get(nm):
        return rec[nm]

    pos, ch = _split_fields(path, [f for f in fields if f != "rgb" and f != "rgba"], get)
    for packed in ("rgb", "rgba"):
        if packed in fields:  # PCL packs 8-bit r, g, b into one float32/uint32
            u = np.ascontiguousarray(rec[packed]).view(np.uint32)
            ch["rgb"] = np.column_stack([(u >> 16) & 255, (u >> 8) & 255, u & 255]).astype(np.uint8)
    return pos, ch


def _pcd_lzf(path: str, f, n: int, cols: list) -> np.ndarray:
    """PCL's ``DATA binary_compressed``: uint32 compressed and uncompressed sizes, then LZF
    of the fields stored column after column (all x, then all y, ...)."""
    import lzf  # python-lzf (pointflow[formats])

    dt = np.dtype([(nm, dt, (ct,)) if ct > 1 else (nm, dt) for nm, dt, ct in cols])
    head = f.read(8)
    if len(head) < 8:
        raise FormatError(path, f"PCD binary_compressed has {len(head)} of the 8 size bytes after DATA")
    csize, usize = np.frombuffer(head, "<u4").tolist()
    if usize != n * dt.itemsize:
        raise FormatError(path, f"PCD binary_compressed promises {usize} uncompressed bytes; "
                                f"{n} points of {dt.itemsize} bytes are {n * dt.itemsize}")
    if usize > 90 * csize + 64:  # an LZF back-reference yields at most 264 bytes from 3
        raise FormatError(path, f"PCD binary_compressed promises {usize} bytes from {csize} compressed bytes, "
                                "more than LZF can expand to")
    comp = f.read(csize)
    if len(comp) < csize:
        raise FormatError(path, f"PCD binary_compressed promises {csize} compressed bytes, file has {len(comp)}")
    try:
        raw = lzf.decompress(comp, usize + 1) if usize else b""  # +1: a longer output shows as too long
    except ValueError as exc:
        raise FormatError(path, f"PCD binary_compressed data is not valid LZF: {exc}") from None
    if raw is None or len(raw) != usize:
        raise FormatError(path, f"PCD binary_compressed data does not decompress to the promised {usize} bytes")
    rec = np.empty(n, dtype=dt)
    off = 0
    for nm, fdt, ct in cols:
        col = np.frombuffer(raw, dtype=fdt, count=n * ct, offset=off)
        rec[nm] = col.reshape(n, ct) if ct > 1 else col
        off += n * ct * fdt.itemsize
    return rec


def write_pcd(path: str, positions: np.ndarray, channels: dict[str, np.ndarray] | None = None,
              binary: bool = True) -> None:
    """Write x, y, z (float32) and 1-D float channels; rgb packed PCL-style."""
    channels = channels or {}
    n = positions.shape[0]
    names, arrs = ["x", "y", "z"], [positions[:, 0], positions[:, 1], positions[:, 2]]
    for k, v in channels.items():
        if k == "rgb":
            u = (v[:, 0].astype(np.uint32) << 16) | (v[:, 1].astype(np.uint32) << 8) | v[:, 2].astype(np.uint32)
            names.append("rgb"); arrs.append(u.view(np.float32))
        else:
            names.append(k); arrs.append(np.asarray(v, np.float32))
    head = ["VERSION .7", "FIELDS " + " ".join(names), "SIZE " + " ".join(["4"] * len(names)),
            "TYPE " + " ".join(["F"] * len(names)), "COUNT " + " ".join(["1"] * len(names)),
            f"WIDTH {n}", "HEIGHT 1", "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {n}",
            f"DATA {'binary' if binary else 'ascii'}"]
    rec = np.empty(n, dtype=[(nm, "<f4") for nm in names])
    for nm, a in zip(names, arrs):
        rec[nm] = a
    with open(path, "wb") as f:
        f.write(("\n".join(head) + "\n").encode())
        if binary:
            f.write(rec.tobytes())
        else:
            np.savetxt(f, np.column_stack([rec[nm] for nm in names]), fmt="%.9g")
