"""NumPy files (``.npy``: an (N, >=3) array or structured x/y/z; ``.npz``: ``xyz``/``points``/
``positions`` or x/y/z arrays and per-point arrays, e.g. Ouster's) and KITTI ``.bin``."""
from __future__ import annotations

import os
import warnings
import zipfile

import numpy as np

from .base import FormatError, check_npy_header, from_array


def read_npy(path: str, columns=None) -> tuple[np.ndarray, dict]:
    with open(path, "rb") as f:
        check_npy_header(path, f, os.fstat(f.fileno()).st_size)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "Reading `.npy` or `.npz` file required additional header parsing")
        return from_array(path, np.load(path, allow_pickle=False))


def read_npz(path: str) -> tuple[np.ndarray, dict]:
    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            if info.filename.endswith(".npy"):
                # a member can expand at most ~1032x by deflate; its header must fit that
                limit = info.compress_size * (1 if info.compress_type == zipfile.ZIP_STORED else 1032)
                with zf.open(info) as f:
                    check_npy_header(path, f, min(info.file_size, limit), info.filename)
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
