"""Bytes on the wire: optional compression and position quantisation of chunk frames.

Declared in the chunk header (docs/wire-format.md, "Encoded chunks") so any language can
produce them:

* ``"codec": "lz4" | "zstd"``: every data frame is one complete LZ4 frame (the LZ4 frame
  format) or one Zstandard frame, holding the bytes the plain format would send.
* ``"shuffle": true`` (only with a codec): before compression each frame's bytes were
  byte-shuffled by element size (all first bytes of the values, then all second bytes...),
  which lets the compressor see the slowly varying high bytes as runs.
* ``positions.dtype`` ``int32`` with ``positions.origin`` ``[x, y, z]`` (float64) and
  ``positions.resolution`` r: the positions are ``origin + q * r``, decoded as float64.

lz4 and zstandard are imported only when a link uses them (extra ``pointflow[remote]``).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from .chunk import ChunkError

CODECS = ("lz4", "zstd")
#: Quantised offsets must fit int32 with room to spare.
_QMAX = 2**31 - 2


def _module(codec: str):
    try:
        if codec == "lz4":
            import lz4.frame

            return lz4.frame
        import zstandard

        return zstandard
    except ImportError:
        raise ChunkError("unsupported_codec", f"codec {codec!r} needs the {'lz4' if codec == 'lz4' else 'zstandard'} "
                         "package: pip install 'pointflow[remote]'") from None


def shuffle(a: np.ndarray) -> bytes:
    """Byte-shuffle: byte 0 of every value, then byte 1, ... (a no-op for 1-byte values)."""
    a = np.ascontiguousarray(a)
    k = a.dtype.itemsize
    if k == 1:
        return a.tobytes()
    return np.ascontiguousarray(a.reshape(-1).view(np.uint8).reshape(-1, k).T).tobytes()


def unshuffle(buf: bytes, itemsize: int) -> bytes:
    if itemsize == 1:
        return buf
    b = np.frombuffer(buf, np.uint8)
    return np.ascontiguousarray(b.reshape(itemsize, -1).T).tobytes()


class Compressor:
    """Compresses frames for one link (keeps the compressor object; not thread-safe)."""

    def __init__(self, codec: str, level: int = 0, shuffle_bytes: bool = True):
        if codec not in CODECS:
            raise ValueError(f"codec must be one of {CODECS}, got {codec!r}")
        self.codec = codec
        self.shuffle = shuffle_bytes
        mod = _module(codec)
        if codec == "zstd":
            self._z = mod.ZstdCompressor(level=level or 3, write_content_size=True)
            self._fn = self._z.compress
        else:
            self._fn = lambda b: mod.compress(b, compression_level=level, store_size=True)

    def frame(self, a: np.ndarray) -> bytes:
        return self._fn(shuffle(a) if self.shuffle else np.ascontiguousarray(a).tobytes())


def decompress(frame: Any, codec: Any, expected: int, itemsize: int, shuffled: bool) -> bytes:
    """The plain bytes of one data frame; ``expected`` bounds the output (no zip bombs)."""
    if codec not in CODECS:
        raise ChunkError("unsupported_codec", f"unknown codec {codec!r}; expected one of {', '.join(CODECS)}")
    mod = _module(codec)
    data = bytes(frame)
    try:
        if codec == "zstd":
            out = mod.ZstdDecompressor().decompress(data, max_output_size=max(1, expected))
        else:
            d = mod.LZ4FrameDecompressor()
            out = d.decompress(data, max_length=max(1, expected)) if expected else d.decompress(data)
    except Exception as exc:  # noqa: BLE001 - both libraries raise their own error types
        raise ChunkError("bad_compression", f"{codec} frame does not decompress: {exc}") from None
    if len(out) != expected:
        raise ChunkError("truncated" if len(out) < expected else "size_mismatch",
                         f"{codec} frame holds {len(out)} bytes, the header promises {expected}")
    return unshuffle(out, itemsize) if shuffled else out


def quantise(pos: np.ndarray, resolution: float) -> tuple[np.ndarray, list[float]] | None:
    """int32 offsets from a per-chunk float64 origin (the chunk's minimum, floored to the
    resolution), or None when the chunk spans too far for int32 or is not finite."""
    if pos.shape[0] == 0:
        return np.zeros((0, 3), np.int32), [0.0, 0.0, 0.0]
    # per-axis min/max on a transposed copy: numpy's axis-0 reduction of an (n, 3) array is
    # about 20x slower than three contiguous ones. NaN and inf propagate into these.
    cols = np.ascontiguousarray(pos.T)
    lo, hi = cols.min(axis=1).astype(np.float64), cols.max(axis=1).astype(np.float64)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        return None
    origin = np.floor(lo / resolution) * resolution
    if ((hi - origin) / resolution).max() > _QMAX:
        return None
    q = np.subtract(pos, origin, dtype=np.float64)  # a new array: the caller's positions stay as they are
    q *= 1.0 / resolution
    np.rint(q, out=q)
    return q.astype(np.int32), [float(v) for v in origin]


def dequantise(q: np.ndarray, origin: Any, resolution: Any) -> np.ndarray:
    if (not isinstance(origin, list) or len(origin) != 3
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in origin)):
        raise ChunkError("bad_header", f"quantised positions need 'origin' [x, y, z], got {origin!r}")
    if not isinstance(resolution, (int, float)) or isinstance(resolution, bool) or not 0 < resolution < 1e9:
        raise ChunkError("bad_header", f"quantised positions need a positive 'resolution', got {resolution!r}")
    return q * float(resolution) + np.asarray(origin, np.float64)
