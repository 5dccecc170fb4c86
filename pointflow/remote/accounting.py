"""``pointflow send``'s accounting identities (the sender kind's ``accounting`` hook;
docs/remote.md)."""
from __future__ import annotations

from typing import Any

from ..stage.accounting import source_balance, sources_of


def send_identities(stages: dict, ring: dict | None, cfg) -> dict[str, Any]:
    """``pointflow send``: points the sources produced = handed to the link + dropped."""
    snd = stages.get("sender", {})
    sources = sources_of(stages)
    acc: dict[str, Any] = {
        **source_balance(sources),
        "sources_sent": sum(v.get("points_out", 0) for v in sources),
        "sender_received": snd.get("points_in", 0),
        "link_sent": snd.get("points_out", 0),
        "sender_dropped": sum(snd.get("drops", {}).values()),
        "sender_queued": snd.get("queued_points", 0),
    }
    acc["sender_balanced"] = acc["sender_received"] == acc["link_sent"] + acc["sender_dropped"] + acc["sender_queued"]
    if not any(v.get("restarts") for v in sources):
        acc["lost_before_sender"] = acc["sources_sent"] - acc["sender_received"]
    return acc
