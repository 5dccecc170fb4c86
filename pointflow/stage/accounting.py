"""What the stages' accounting identities share (each stage's own identities live beside
it, named by its kind's ``accounting`` hook): the kind that writes the ring, and the
sources' balance, which both a pipeline's ingest and ``pointflow send``'s sender report."""
from __future__ import annotations

from typing import Any

#: The kind that writes the ring: its counts are checked against the ring's own.
RING_WRITER = "ingest"


def source_balance(sources: list[dict]) -> dict[str, Any]:
    """The sources' own balance: points their transports produced = sent on to ingest (or
    the sender) + dropped there by reason (``hwm``: the send queue stayed full, e.g. a link
    delivering faster than ingest takes; ``encode_error``)."""
    by_reason: dict[str, int] = {}
    for v in sources:
        for r, n in (v.get("drops") or {}).items():
            by_reason[r] = by_reason.get(r, 0) + n
    out: dict[str, Any] = {
        "sources_received": sum(v.get("points_in", 0) for v in sources),
        "sources_forwarded": sum(v.get("points_out", 0) for v in sources),
        "sources_dropped": sum(by_reason.values()),
        "sources_dropped_by_reason": by_reason,
    }
    out["sources_balanced"] = out["sources_received"] == out["sources_forwarded"] + out["sources_dropped"]
    return out


def sources_of(stages: dict) -> list[dict]:
    """The stats of the run's source stages."""
    return [v for v in stages.values() if v.get("kind") == "source"]
