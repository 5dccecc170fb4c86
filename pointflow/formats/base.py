"""What every reader shares: the error, the failures a corrupt file raises, the checks of a
header's counts against the bytes that follow, and positions/channels from named fields."""
from __future__ import annotations

import os
import struct
import tokenize
import warnings
import zipfile
from typing import Sequence

import numpy as np

from ..errors import KeyedError


class FormatError(KeyedError):
    """A point file that cannot be read; ``key`` (also ``path``) is the file."""

    @property
    def path(self) -> str:
        return self.key



#: What numpy, zipfile and the header parsers raise on a corrupt file (zipfile: a damaged or
#: encrypted archive; tokenize/SyntaxError: an .npy header dict that does not parse;
#: MemoryError: a count the size checks let through).
READ_FAILURES = (OSError, ValueError, KeyError, IndexError, EOFError, zipfile.BadZipFile, NotImplementedError,
                  tokenize.TokenError, SyntaxError, struct.error, MemoryError, OverflowError)


def check_npy_header(path: str, f, nbytes: int, member: str = "") -> None:
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


RGB_NAMES = (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue"))


def split_fields(path: str, names: Sequence[str], get) -> tuple[np.ndarray, dict]:
    """positions from x/y/z fields, rgb from red/green/blue, the rest as channels."""
    lower = {n.lower(): n for n in names}
    if not all(k in lower for k in ("x", "y", "z")):
        raise FormatError(path, f"no x, y, z fields (fields: {', '.join(names)})")
    pos = np.column_stack([np.asarray(get(lower[k]), np.float64) for k in ("x", "y", "z")])
    used = {lower["x"], lower["y"], lower["z"]}
    ch: dict[str, np.ndarray] = {}
    for trio in RGB_NAMES:
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


def from_array(path: str, arr: np.ndarray) -> tuple[np.ndarray, dict]:
    if arr.dtype.names:
        return split_fields(path, arr.dtype.names, lambda n: arr[n])
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


def check_count(path: str, f, n: int, values: int, what: str, unit: str) -> None:
    """A header's element count must fit the bytes after the header (checked before numpy
    allocates that many rows): at least one byte per binary value, two (a digit and a
    separator) per ascii value."""
    left = os.fstat(f.fileno()).st_size - f.tell()
    if n < 0 or n * max(values, 1) > left:
        raise FormatError(path, f"{what} header promises {n} {unit} of {values} values, "
                                f"only {left} bytes follow the header")


def loadtxt(f, n: int, values: int) -> np.ndarray:
    """Up to n rows of numbers (an empty body gives 0 rows, not numpy's warning)."""
    if not n:
        return np.zeros((0, values))
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "loadtxt: input contained no data")
        return np.loadtxt(f, max_rows=n, ndmin=2)
