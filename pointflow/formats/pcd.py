"""PCD (ascii, binary, binary_compressed via python-lzf): read and write."""
from __future__ import annotations

import numpy as np

from .base import FormatError, check_count, loadtxt, split_fields


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
            check_count(path, f, n, sum(c[2] for c in cols), "PCD", "points")
        if mode == "ascii":
            arr = loadtxt(f, n, sum(c[2] for c in cols))
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
            rec = pcd_lzf(path, f, n, cols)
        else:
            raise FormatError(path, f"PCD DATA {mode!r} is not supported (ascii, binary, binary_compressed)")
    fields = [c[0] for c in cols if not c[0].startswith("_pad") and c[2] == 1]

    def get(nm):
        return rec[nm]

    pos, ch = split_fields(path, [f for f in fields if f != "rgb" and f != "rgba"], get)
    for packed in ("rgb", "rgba"):
        if packed in fields:  # PCL packs 8-bit r, g, b into one float32/uint32
            u = np.ascontiguousarray(rec[packed]).view(np.uint32)
            ch["rgb"] = np.column_stack([(u >> 16) & 255, (u >> 8) & 255, u & 255]).astype(np.uint8)
    return pos, ch


def pcd_lzf(path: str, f, n: int, cols: list) -> np.ndarray:
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
