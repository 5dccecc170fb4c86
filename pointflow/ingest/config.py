"""The ``sources:`` entries and the ``ingest:`` section (the loader, pointflow/config.py,
assembles them; each transport checks its own ``options``)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

from ..stage.endpoints import Endpoint
from ..typed import at_least_one, check


#: Ingest's link: sources -> ingest (PULL bound by ingest).
ENDPOINTS = (Endpoint("ingest", "ingest", "sources -> ingest (PULL bound by ingest)"),)


@dataclass
class SourceConfig:
    """One source process. ``transport`` is a built-in name, an entry-point name from the
    ``pointflow.transports`` group, or ``package.module:Class``."""

    transport: str
    name: str = ""
    options: dict[str, Any] = field(default_factory=dict)
    #: True when the source runs elsewhere (another program or machine sending the wire
    #: format to ``endpoints.ingest``); the supervisor does not start it.
    external: bool = False
    #: The coordinate frame of this source's clouds when its data carry none (docs/frames.md).
    frame_id: Optional[str] = None


@dataclass
class IngestConfig:
    max_chunk_points: int = field(default=5_000_000, metadata=check(at_least_one))
    coalesce_points: int = field(default=20_000, metadata=check(at_least_one))
    queue_max_batches: int = field(default=64, metadata=check(at_least_one))
    receive_hwm: int = field(default=256, metadata=check(at_least_one))
    adaptive_thinning: bool = False
