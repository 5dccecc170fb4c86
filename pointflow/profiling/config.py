"""The ``tracing:`` section: whether the stages record spans, and how they batch them."""
from __future__ import annotations

from dataclasses import dataclass, field

from ..typed import at_least_one, check, positive


@dataclass
class TracingConfig:
    enabled: bool = True
    #: Spans are sent in batches of this many (or every flush interval).
    batch: int = field(default=256, metadata=check(at_least_one))
    flush_ms: float = field(default=100.0, metadata=check(positive))
