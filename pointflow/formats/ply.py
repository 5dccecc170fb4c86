"""PLY (ascii, binary little/big endian): read and write."""
from __future__ import annotations

import numpy as np

from .base import FormatError, check_count, loadtxt, split_fields


PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
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
                    if t[1] not in PLY_TYPES:
                        raise FormatError(path, f"unknown PLY property type {t[1]!r}")
                    elements[-1][2].append((t[2], PLY_TYPES[t[1]]))
            elif t[0] == "end_header":
                break
        if not elements or elements[0][0] != "vertex":
            raise FormatError(path, "PLY has no leading 'vertex' element")
        _, n, props = elements[0]
        check_count(path, f, n, len(props), "PLY", "vertices")
        if fmt == "ascii":
            arr = loadtxt(f, n, len(props))
            if arr.shape[0] != n:
                raise FormatError(path, f"PLY promises {n} vertices, file has {arr.shape[0]}")
            names = [p[0] for p in props]
            return split_fields(path, names, lambda nm: arr[:, names.index(nm)].astype(np.dtype(dict(props)[nm])))
        if fmt not in ("binary_little_endian", "binary_big_endian"):
            raise FormatError(path, f"unknown PLY format {fmt!r}")
        end = "<" if fmt == "binary_little_endian" else ">"
        dt = np.dtype([(name, end + t) for name, t in props])
        buf = f.read(n * dt.itemsize)
        if len(buf) < n * dt.itemsize:
            raise FormatError(path, f"PLY promises {n} vertices ({n * dt.itemsize} bytes), file has {len(buf)}")
        rec = np.frombuffer(buf, dtype=dt)
        return split_fields(path, dt.names, lambda nm: rec[nm].astype(rec[nm].dtype.newbyteorder("=")))


def write_ply(path: str, positions: np.ndarray, channels: dict[str, np.ndarray] | None = None,
              binary: bool = True) -> None:
    """Write vertices (x, y, z as double, 1-D channels with their dtype, rgb as uchar)."""
    channels = channels or {}
    rev = {v: k for k, v in PLY_TYPES.items() if k in ("char", "uchar", "short", "ushort", "int", "uint", "float", "double")}
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
