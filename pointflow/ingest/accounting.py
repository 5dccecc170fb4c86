"""Ingest's accounting identities (its kind's ``accounting`` hook; docs/architecture.md,
"Accounting")."""
from __future__ import annotations

from typing import Any

from ..stage.accounting import RING_WRITER, source_balance, sources_of


def ingest_identities(stages: dict, ring: dict | None, cfg) -> dict[str, Any]:
    """Ingest's balance (points of accepted chunks = written + dropped by reason; rejected
    messages are counted per message and reason), the ring agreeing with ingest, and
    points the sources sent that ingest never saw (lost in the socket buffers of a killed
    ingest; known only without external sources and while no source was killed, since a
    killed source's last counts die with it); with link sources, the link's balance."""
    ing = stages.get(RING_WRITER, {})
    rejected = ing.get("rejected", {})
    acc: dict[str, Any] = {
        "ingest_received": ing.get("points_in", 0),
        "ingest_written": ing.get("points_out", 0),
        "ingest_dropped": sum(ing.get("drops", {}).values()),
        "ingest_rejected_messages": sum(v for v in rejected.values() if isinstance(v, (int, float)))
        if isinstance(rejected, dict) else 0,
    }
    acc["ingest_balanced"] = acc["ingest_received"] == acc["ingest_written"] + acc["ingest_dropped"]
    # written by an ingest that died before reporting them, read back from the ring
    acc["ingest_unreported_written"] = ing.get("unreported_written", 0)
    if ring:
        # As of ingest's last report (the ring's counter read by ingest with its counts),
        # or as read back after it died or the run stopped: then both sides hold the same
        # writes. The counter now runs ahead of any report while ingest writes (the pushes
        # since its last heartbeat); comparing it with the report read ring_agrees: false
        # in live samples under load (issue 31).
        now_written = ring.get("total_written")
        acc["ring_written"] = ing.get("ring_written_at_report", 0) if RING_WRITER in stages else now_written
        acc["ring_written_now"] = now_written
        acc["ring_agrees"] = acc["ring_written"] == acc["ingest_written"]
    sources = sources_of(stages)
    acc.update(source_balance(sources))
    if not any(s.external for s in cfg.sources):
        acc["sources_sent"] = sum(v.get("points_out", 0) for v in sources)
        if any(v.get("restarts") for v in sources):
            # a killed source's sends since its last heartbeat died with it
            acc["lost_before_ingest"] = None
        else:
            acc["lost_before_ingest"] = acc["sources_sent"] - acc["ingest_received"]
    link = [v for v in sources if "transport_link_sent" in v]
    if link:
        # zmq sources fed by `pointflow send` (docs/remote.md): what the senders sent
        # since this pipeline joined = what arrived + what the link lost
        acc["link_sent"] = sum(v.get("transport_link_sent", 0) for v in link)
        acc["link_received"] = sum(v.get("transport_link_received", 0) for v in link)
        acc["lost_in_transit"] = sum(v.get("transport_lost_in_transit", 0) for v in link)
        acc["lost_in_transit_by_source"] = {k.split(":", 1)[1]: n for v in link for k, n in v.items()
                                            if k.startswith("transport_lost_in_transit:")}
        # a zenoh source's own bounded queue (docs/remote.md, "The Zenoh engine")
        dropped = [v["transport_receive_queue_full"] for v in link if "transport_receive_queue_full" in v]
        if dropped:
            acc["receive_queue_full"] = sum(dropped)
        acc["link_balanced"] = acc["link_sent"] == acc["link_received"] + acc["lost_in_transit"] \
            + acc.get("receive_queue_full", 0)
    return acc
