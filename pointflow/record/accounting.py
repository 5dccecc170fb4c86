"""The recording's accounting identities (the recorder kind's ``accounting`` hook;
docs/record.md)."""
from __future__ import annotations

from typing import Any

from ..stage.accounting import RING_WRITER


def record_identities(stages: dict, ring: dict | None, cfg) -> dict[str, Any]:
    """The recording (docs/record.md): ingest offers the recorder each chunk it pushes to
    the ring, sends it or drops it (never waits); the recorder writes what it received or
    drops it (disk full); what was sent but never received died in a killed recorder's
    socket (``lost_before_recorder``, 0 on a clean stop)."""
    ing, rec = stages.get(RING_WRITER, {}), stages.get("recorder", {})
    drops = ing.get("drops", {})
    acc: dict[str, Any] = {
        "record_offered": ing.get("record_offered", 0),
        "record_sent": ing.get("record_sent", 0),
        "record_dropped": ing.get("record_dropped", 0),
        "recorder_received": rec.get("points_in", 0),
        "recorder_written": rec.get("points_out", 0),
        "recorder_dropped": sum(rec.get("drops", {}).values()),
    }
    # what ingest offered is what it handed the ring: written, or refused by the ring
    acc["record_covers_ring"] = acc["record_offered"] == (
        ing.get("points_out", 0) + drops.get("out_of_range", 0) + drops.get("ring_full", 0)) \
        if not ing.get("restarts") else None  # a killed ingest's points_out is taken from the ring
    acc["record_tap_balanced"] = acc["record_offered"] == acc["record_sent"] + acc["record_dropped"]
    acc["recorder_balanced"] = acc["recorder_received"] == acc["recorder_written"] + acc["recorder_dropped"]
    # a killed ingest's or recorder's counts since its last heartbeat died with it
    acc["lost_before_recorder"] = acc["record_sent"] - acc["recorder_received"] \
        if not (ing.get("restarts") or rec.get("restarts")) else None
    return acc
