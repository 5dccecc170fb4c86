"""The shared-memory point ring: bounded store, eviction, staleness, double-buffered slabs."""
from .layout import ChannelSpec, RingAttachError, RingConfigError, RingError, RingLayout
from .ring import (
    K_CANDIDATES,
    Changes,
    PointRecord,
    PointRing,
    PushResult,
    RingStats,
    Snapshot,
    TemporalStats,
)

__all__ = [
    "ChannelSpec", "RingLayout", "RingError", "RingAttachError", "RingConfigError", "PointRing", "PushResult",
    "RingStats", "Snapshot", "PointRecord", "TemporalStats", "Changes", "K_CANDIDATES",
]
