"""Point-cloud files: one reader per format, in a table keyed by suffix.

Every reader returns ``(positions, channels)``: positions (N, 3) float64 (float32 where
the format stores float32: KITTI, Ouster npz) and a dict of per-point channels in the
file's own dtypes; ``rgb`` is (N, 3). Readers are vectorised (numpy structured dtypes,
``np.loadtxt``); a malformed file raises :class:`FormatError` naming the file and what
is wrong. The ``file`` source (ingest) and the map library read files here.

Formats: LAS/LAZ (laspy; intensity, classification, gps_time, rgb, return_number), PLY
(ascii, binary little/big endian), PCD (ascii, binary, binary_compressed via python-lzf),
NPY ((N,>=3) array or structured x/y/z), NPZ (``xyz``/``points``/``positions`` or x/y/z
arrays + per-point arrays, e.g. Ouster ``range``, ``reflectivity``), CSV/XYZ/TXT (header
row optional), KITTI ``.bin`` (float32 x, y, z, reflectance -> ``intensity``).

The API: :func:`read` (a whole file), :func:`reader_for` (the reader of a path),
:data:`READERS` (the table), :func:`iter_las` and :func:`las_point_count` (LAS/LAZ in
pieces), :func:`write_ply` and :func:`write_pcd`.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import numpy as np

from .arrays import read_kitti, read_npy, read_npz
from .base import READ_FAILURES, FormatError
from .las import LAS_PIECE_POINTS, iter_las, las_point_count, las_record_channels, read_las
from .pcd import read_pcd, write_pcd
from .ply import read_ply, write_ply
from .text import read_text

#: What a reader is called with: the path and the column names of a text file (or None).
ReadFn = Callable[[str, Optional[Sequence[str]]], "tuple[np.ndarray, dict]"]


@dataclass(frozen=True)
class Reader:
    """One format: its name (the suffix without its dot) and its reader."""

    name: str
    label: str
    read: ReadFn


def _no_columns(fn: Callable[[str], "tuple[np.ndarray, dict]"]) -> ReadFn:
    return lambda path, columns=None: fn(path)


#: The readers by suffix (lower case, no dot); a format's ``format`` option names one.
READERS: dict[str, Reader] = {r.name: r for r in (
    Reader("las", "LAS", read_las), Reader("laz", "LAZ", read_las),
    Reader("ply", "PLY", _no_columns(read_ply)), Reader("pcd", "PCD", _no_columns(read_pcd)),
    Reader("npy", "NumPy array", read_npy), Reader("npz", "NumPy archive", _no_columns(read_npz)),
    Reader("csv", "CSV", read_text), Reader("xyz", "XYZ text", read_text), Reader("txt", "text columns", read_text),
    Reader("bin", "KITTI .bin", _no_columns(read_kitti)),
)}

#: The suffixes known (the keys of :data:`READERS`).
FORMATS = tuple(READERS)


def detect_format(path: str) -> str:
    """The format of ``path`` by its suffix; :class:`FormatError` naming the file and the
    suffixes known when none matches."""
    ext = os.path.splitext(path)[1].lower().lstrip(".")
    if ext not in READERS:
        raise FormatError(path, f"unknown point-cloud format {ext!r}; expected one of {', '.join(FORMATS)} (or set 'format')")
    return ext


def reader_for(path: str, fmt: str | None = None) -> Reader:
    """The reader of ``path``: the one named by ``fmt``, else the one of its suffix."""
    name = (fmt or detect_format(path)).lower()
    reader = READERS.get(name)
    if reader is None:
        raise FormatError(path, f"unsupported format {name!r}; expected one of {', '.join(FORMATS)}")
    return reader


def read(path: str, fmt: str | None = None, columns: Sequence[str] | None = None) -> tuple[np.ndarray, dict]:
    """Read a whole file: ``(positions, channels)``; every failure is a :class:`FormatError`."""
    reader = reader_for(path, fmt)
    try:
        return reader.read(path, columns)
    except FormatError:
        raise
    except READ_FAILURES as exc:
        raise FormatError(path, f"cannot read as {reader.name}: {type(exc).__name__}: "
                                f"{' '.join(str(exc).split())}") from None



__all__ = ["FORMATS", "FormatError", "LAS_PIECE_POINTS", "READERS", "Reader", "detect_format", "iter_las",
           "las_point_count", "las_record_channels", "read", "reader_for", "write_pcd", "write_ply"]
