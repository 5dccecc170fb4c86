"""The shared-memory point ring: bounded store, eviction, staleness, double-buffered slabs.

See docs/ring.md.
"""
from .handoff import Handoff, SlabReader, SlabWriter
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
from .slabs import SlabPair, SlabView

__all__ = [
    "ChannelSpec", "RingLayout", "RingError", "RingAttachError", "RingConfigError", "PointRing", "PushResult",
    "RingStats", "Snapshot", "PointRecord", "TemporalStats", "Changes", "K_CANDIDATES",
    "SlabPair", "SlabView", "Handoff", "SlabWriter", "SlabReader",
]
