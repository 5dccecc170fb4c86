"""The ``frames:`` config block (docs/frames.md), validated at load; errors name the key."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal, Optional, Union

from ..typed import ConfigError, check, non_negative, positive


@dataclass
class StaticTransformConfig:
    """A fixed extrinsic: points in ``child`` map into ``parent``. Give the rotation as
    ``rpy_deg`` (roll, pitch, yaw about fixed x, y, z) or ``quaternion`` (x, y, z, w), not both."""

    parent: str
    child: str
    translation: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    rpy_deg: Optional[list[float]] = None
    quaternion: Optional[list[float]] = None


@dataclass
class DeskewConfig:
    """An explicit per-point time field: ``unit`` of its values, relative to the cloud's
    header stamp (``header``) or absolute (``absolute``, since the epoch)."""

    field: str
    unit: Literal["ns", "us", "s"] = "ns"
    reference: Literal["header", "absolute"] = "header"


@dataclass
class FramesConfig:
    """Put every point in one fixed frame at ingest (tf2-like buffer, extrinsics, deskew)."""

    #: The frame the ring holds points in; null = points stay as sent (no transform).
    fixed: Optional[str] = None
    #: How long a cloud may wait for its transform before it is dropped (``no_transform``).
    tf_wait_ms: float = field(default=200.0, metadata=check(non_negative))
    #: At most this many points wait for transforms; past it the oldest cloud gives up early.
    max_wait_points: int = field(default=2_000_000, metadata=check(positive))
    #: History kept per dynamic transform edge, seconds.
    history_s: float = field(default=10.0, metadata=check(positive))
    #: Extrinsics for sources that publish none.
    static: list[StaticTransformConfig] = field(default_factory=list)
    #: ``auto`` (by field name and type), ``off``, or an explicit field.
    deskew: Union[Literal["auto", "off"], DeskewConfig] = "auto"


def check_frames(f: FramesConfig, path: str = "frames") -> None:
    """Semantic checks beyond types (the buffer raises the same errors at run time)."""
    from .buffer import FrameError, TransformBuffer

    buf = TransformBuffer()
    for i, s in enumerate(f.static):
        p = f"{path}.static[{i}]"
        for key in ("parent", "child"):
            if not getattr(s, key).strip():
                raise ConfigError(f"{p}.{key}", "must be a frame name")
        if len(s.translation) != 3:
            raise ConfigError(f"{p}.translation", f"must be [x, y, z], got {s.translation!r}")
        if s.rpy_deg is not None and s.quaternion is not None:
            raise ConfigError(f"{p}.quaternion", "give either rpy_deg or quaternion, not both")
        if s.rpy_deg is not None and len(s.rpy_deg) != 3:
            raise ConfigError(f"{p}.rpy_deg", f"must be [roll, pitch, yaw] in degrees, got {s.rpy_deg!r}")
        if s.quaternion is not None:
            if len(s.quaternion) != 4:
                raise ConfigError(f"{p}.quaternion", f"must be [x, y, z, w], got {s.quaternion!r}")
            norm = math.sqrt(sum(v * v for v in s.quaternion))
            if abs(norm - 1.0) > 1e-3:
                raise ConfigError(f"{p}.quaternion", f"must be a unit quaternion [x, y, z, w] (length 1), "
                                  f"got length {norm:.6g}")
        try:
            buf.set_transform(s.parent, s.child, 0, s.translation, static_rotation(s), static=True)
        except FrameError as exc:
            raise ConfigError(p, str(exc)) from None
    if isinstance(f.deskew, DeskewConfig) and not f.deskew.field:
        raise ConfigError(f"{path}.deskew.field", "must name the per-point time field")
    if f.fixed is not None and not f.fixed.strip():
        raise ConfigError(f"{path}.fixed", "must be a frame name or null")


def static_rotation(s: StaticTransformConfig) -> list[float]:
    """The (x, y, z, w) quaternion of a static entry."""
    from .rotation import from_rpy

    if s.quaternion is not None:
        return list(s.quaternion)
    r = s.rpy_deg or [0.0, 0.0, 0.0]
    return list(from_rpy(*(math.radians(v) for v in r)))
