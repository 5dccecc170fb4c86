"""PointFlow's quantised binary frame (websocket), decoded and encoded with numpy.

Layout, little-endian::

    u16 N, u8 M, u8 flags (0), f32 xmin, f32 ymin, f32 zmin, f32 scale     (20 bytes)
    N x (u16 qx, u16 qy, u16 qz)
    N x M u16 attributes (point-major: the M values of point 0, then of point 1, ...)

``x = xmin + qx / 65535 * scale`` (one scale for all axes); attribute ``j`` maps linearly
onto its schema range ``[min_j, max_j]``. A frame shorter than declared, longer than
declared, with non-zero flags or with ``M`` different from the schema is rejected.
``N = 0`` is an empty chunk.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..chunk import ChunkError, PointChunk

HEADER = struct.Struct("<HBBffff")
assert HEADER.size == 20


@dataclass
class AttributeRange:
    """One quantised attribute: its channel name and the range 0..65535 maps onto."""

    name: str
    min: float = 0.0
    max: float = 1.0


def decode_quantised(buf: bytes | bytearray | memoryview, schema: Sequence[AttributeRange],
                     source_id: str = "") -> PointChunk:
    """Decode one frame; raises :class:`ChunkError` (``truncated``, ``size_mismatch``,
    ``schema_mismatch``, ``bad_flags``)."""
    mv = memoryview(buf).cast("B")
    if mv.nbytes < HEADER.size:
        raise ChunkError("truncated", f"quantised frame of {mv.nbytes} bytes is shorter than its 20-byte header")
    n, m, flags, xmin, ymin, zmin, scale = HEADER.unpack_from(mv, 0)
    if flags != 0:
        raise ChunkError("bad_flags", f"quantised frame flags must be 0, got {flags}")
    if m != len(schema):
        raise ChunkError("schema_mismatch", f"quantised frame has {m} attribute(s), the schema declares {len(schema)}")
    need = HEADER.size + 6 * n + 2 * n * m
    if mv.nbytes < need:
        raise ChunkError("truncated", f"quantised frame declares {n} points x {m} attributes ({need} bytes) but has {mv.nbytes}")
    if mv.nbytes > need:
        raise ChunkError("size_mismatch", f"quantised frame has {mv.nbytes - need} bytes beyond the {need} its header declares")
    if not all(np.isfinite((xmin, ymin, zmin, scale))):
        raise ChunkError("bad_header", "quantised frame has a non-finite origin or scale")
    q = np.frombuffer(mv, dtype="<u2", count=3 * n, offset=HEADER.size).reshape(n, 3)
    pos = q * (scale / 65535.0) + np.array([xmin, ymin, zmin], np.float64)
    chans: dict[str, np.ndarray] = {}
    if m:
        a = np.frombuffer(mv, dtype="<u2", count=n * m, offset=HEADER.size + 6 * n).reshape(n, m)
        for j, attr in enumerate(schema):
            chans[attr.name] = (attr.min + a[:, j] * ((attr.max - attr.min) / 65535.0)).astype(np.float32)
    return PointChunk(positions=pos, channels=chans, source_id=source_id)


def encode_quantised(positions: np.ndarray, attributes: dict[str, np.ndarray] | None = None,
                     schema: Sequence[AttributeRange] = ()) -> bytes:
    """Encode points into one frame (for tests and senders); N must fit in a u16."""
    pos = np.asarray(positions, np.float64).reshape(-1, 3)
    n = pos.shape[0]
    if n > 65535:
        raise ValueError(f"a quantised frame holds at most 65535 points, got {n}")
    lo = pos.min(axis=0) if n else np.zeros(3)
    scale = float((pos.max(axis=0) - lo).max()) if n else 0.0
    scale = scale or 1.0
    q = np.rint((pos - lo) / scale * 65535.0).clip(0, 65535).astype("<u2")
    parts = [HEADER.pack(n, len(schema), 0, *(float(v) for v in lo), scale), q.tobytes()]
    if schema:
        a = np.empty((n, len(schema)), "<u2")
        for j, attr in enumerate(schema):
            v = np.asarray((attributes or {})[attr.name], np.float64)
            a[:, j] = np.rint((v - attr.min) / (attr.max - attr.min) * 65535.0).clip(0, 65535)
        parts.append(a.tobytes())
    return b"".join(parts)
