"""CSV / XYZ / TXT: numbers in columns, a header row optional."""
from __future__ import annotations

import warnings
from typing import Sequence

import numpy as np

from .base import FormatError, split_fields


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
    pos, ch = split_fields(path, names, lambda n: arr[:, idx[n]])
    with np.errstate(over="ignore"):  # a value beyond float32 becomes inf, as a float32 file would hold it
        return pos, {k: (v.astype(np.float32) if v.dtype == np.float64 else v) for k, v in ch.items()}
