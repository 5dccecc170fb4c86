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
from typing import Iterator, Sequence

import numpy as np

FORMATS = ("las", "laz", "ply", "pcd", "npy", "npz", "csv", "xyz", "txt", "bin")


class FormatError(ValueError):
    def __init__(self, path: str, message: str):
        super().__init__(f"{path}: {message}")
        self.path = path


def detect_format(path: str) -> str:
    ext = os.path.splitext(path)[1].lower().lstrip(".")
    if ext not in FORMATS:
        raise FormatError(path, f"unknown point-cloud format {ext!r}; expected one of {', '.join(FORMATS)} (or set 'format')")
    return ext


def read_points(path: str, fmt: str | None = None, columns: Sequence[str] | None = None):
    """Read a whole file."""
    fmt = (fmt or detect_format(path)).lower()
    try:
        if fmt in ("las", "laz"):
            pos, ch = None, None
            for pos_c, ch_c in iter_las(path, 1 << 62):
                pos, ch = pos_c, ch_c
            if pos is None:
                return np.zeros((0, 3)), {}
            return pos, ch
        if fmt == "ply":
            return read_ply(path)
        if fmt == "pcd":
            return read_pcd(path)
        if fmt == "npy":
            return _from_array(path, np.load(path, allow_pickle=False))
        if fmt == "npz":
            return read_npz(path)
        if fmt in ("csv", "xyz", "txt"):
            return read_text(path, columns)
        if fmt == "bin":
            return read_kitti(path)
    except FormatError:
        raise
    except (OSError, ValueError, KeyError, IndexError, EOFError) as exc:
        raise FormatError(path, f"cannot read as {fmt}: {type(exc).__name__}: {exc}") from None
    raise FormatError(path, f"unsupported format {fmt!r}")


# --------------------------------------------------------------------------- LAS / LAZ
def iter_las(path: str, chunk_points: int) -> Iterator[tuple[np.ndarray, dict]]:
    """LAS/LAZ in pieces of ``chunk_points`` (laspy's chunk iterator: big files stream)."""
    import laspy

    with laspy.open(path) as f:
        dims = set(f.header.point_format.dimension_names)
        for pts in f.chunk_iterator(chunk_points):
            pos = np.column_stack([np.asarray(pts.x, np.float64), np.asarray(pts.y, np.float64),
                                   np.asarray(pts.z, np.float64)])
            ch: dict[str, np.ndarray] = {"intensity": np.asarray(pts.intensity, np.uint16),
                                         "classification": np.asarray(pts.classification, np.uint8),
                                         "return_number": np.asarray(pts.return_number, np.uint8)}
            if "gps_time" in dims:
                ch["gps_time"] = np.asarray(pts.gps_time, np.float64)
            if {"red", "green", "blue"} <= dims:
                ch["rgb"] = np.column_stack([np.asarray(pts.red), np.asarray(pts.green), np.asarray(pts.blue)]).astype(np.uint16)
            yield pos, ch


def las_point_count(path: str) -> int:
    import laspy

    with laspy.open(path) as f:
        return int(f.header.point_count)


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
    if arr.shape[1] >= 4:
        ch["intensity"] = np.ascontiguousarray(arr[:, 3]).astype(np.float32)
    for j in range(4, arr.shape[1]):
        ch[f"col{j}"] = np.ascontiguousarray(arr[:, j]).astype(np.float32)
    return pos, ch


# --------------------------------------------------------------------------- NPZ / KITTI
def read_npz(path: str) -> tuple[np.ndarray, dict]:
    with np.load(path, allow_pickle=False) as z:
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
    raw = np.fromfile(path, dtype="<f4")
    if raw.size % 4:
        raise FormatError(path, f"KITTI .bin size {raw.size * 4} bytes is not a multiple of 16 (x, y, z, reflectance)")
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
    arr = np.loadtxt(path, delimiter=delim, skiprows=skip, ndmin=2, comments="#")
    if arr.shape[1] < 3:
        raise FormatError(path, f"text file has {arr.shape[1]} column(s); need at least x, y, z")
    if names is None:
        names = ["x", "y", "z", "intensity"][:arr.shape[1]] + [f"col{j}" for j in range(4, arr.shape[1])]
    if len(names) != arr.shape[1]:
        raise FormatError(path, f"{len(names)} column names for {arr.shape[1]} columns")
    idx = {n: j for j, n in enumerate(names)}
    pos, ch = _split_fields(path, names, lambda n: arr[:, idx[n]])
    return pos, {k: (v.astype(np.float32) if v.dtype == np.float64 else v) for k, v in ch.items()}


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
        if fmt == "ascii":
            arr = np.loadtxt(f, max_rows=n, ndmin=2) if n else np.zeros((0, len(props)))
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
            dt = np.dtype(f"<{kinds[ty]}{sz}")
            cols.append((nm if nm != "_" else f"_pad{len(cols)}", dt, ct))
        mode = meta["DATA"][0].lower()
        if mode == "ascii":
            arr = np.loadtxt(f, ndmin=2, max_rows=n) if n else np.zeros((0, sum(c[2] for c in cols)))
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
