"""The normalised unit of data every transport produces and ingest consumes."""
from __future__ import annotations

import itertools
import os
import time
from dataclasses import dataclass, field

from .errors import Error

import numpy as np

#: dtypes a channel may carry on the wire and into ingest.
SUPPORTED_DTYPES: tuple[str, ...] = (
    "uint8", "int8", "uint16", "int16", "uint32", "int32", "uint64", "int64",
    "float32", "float64",
)

_trace_counter = itertools.count(1)


def new_trace_id() -> int:
    """A trace id unique across processes of one machine for a run (pid in the high bits)."""
    return ((os.getpid() & 0xFFFFF) << 40) | (next(_trace_counter) & 0xFFFFFFFFFF)


class ChunkError(Error, ValueError):
    """A chunk is malformed; ``reason`` is a short machine-readable key counted in stats."""

    def __init__(self, reason: str, message: str):
        super().__init__(f"{reason}: {message}")
        self.reason = reason
        self.message = message


@dataclass
class PointChunk:
    """A batch of points from one source.

    ``positions`` is (N, 3) float64 or float32 in world coordinates (float64 keeps
    georeferenced data exact until the ring subtracts its origin). ``channels`` maps a
    name to an (N,) or (N, k) array (``rgb`` is (N, 3) uint8 or uint16).
    Times are ``time.monotonic_ns()`` values, comparable across processes on one machine;
    ``stamp_ns`` is the data's own capture time when the source has one (a ROS
    ``header.stamp``, ns since the epoch; 0 = unknown), carried unchanged. ``frame_id`` names
    the coordinate frame the positions are in (a ROS ``header.frame_id``; "" = none given),
    used by ingest's frames step (docs/frames.md).
    """

    positions: np.ndarray
    channels: dict[str, np.ndarray] = field(default_factory=dict)
    source_id: str = ""
    seq: int = 0
    trace_id: int = 0
    t_sent_ns: int = 0
    t_recv_ns: int = 0
    stamp_ns: int = 0
    frame_id: str = ""

    def __len__(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n(self) -> int:
        return int(self.positions.shape[0])

    def validate(self, max_points: int | None = None) -> None:
        """Raise :class:`ChunkError` naming what is wrong; cheap (no per-point work)."""
        p = self.positions
        if not isinstance(p, np.ndarray):
            raise ChunkError("bad_positions", f"positions must be a numpy array, got {type(p).__name__}")
        if p.ndim != 2 or p.shape[1] != 3:
            raise ChunkError("bad_positions", f"positions must have shape (N, 3), got {p.shape}")
        if p.dtype not in (np.float32, np.float64):
            raise ChunkError("bad_dtype", f"positions must be float32 or float64, got {p.dtype}")
        n = p.shape[0]
        if max_points is not None and n > max_points:
            raise ChunkError("too_large", f"chunk has {n} points, more than the configured maximum {max_points}")
        for name, arr in self.channels.items():
            if not isinstance(arr, np.ndarray):
                raise ChunkError("bad_channel", f"channel {name!r} must be a numpy array")
            if arr.dtype.name not in SUPPORTED_DTYPES:
                raise ChunkError("bad_dtype", f"channel {name!r} has unsupported dtype {arr.dtype}")
            if arr.ndim not in (1, 2) or arr.shape[0] != n:
                raise ChunkError(
                    "length_mismatch",
                    f"channel {name!r} has shape {arr.shape}, expected ({n},) or ({n}, k)",
                )

    @classmethod
    def from_arrays(cls, positions, source_id: str = "", seq: int = 0, **channels) -> "PointChunk":
        """Convenience constructor stamping a fresh trace id and send time."""
        pos = np.asarray(positions)
        if pos.dtype not in (np.float32, np.float64):
            pos = pos.astype(np.float64)
        return cls(
            positions=pos,
            channels={k: np.asarray(v) for k, v in channels.items()},
            source_id=source_id,
            seq=seq,
            trace_id=new_trace_id(),
            t_sent_ns=time.monotonic_ns(),
        )
