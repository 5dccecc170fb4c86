"""Where every point went: the accounting identities of ``stats()["accounting"]``.

Each stage kind names the identities its counters enter (:attr:`StageKind.accounting`,
a ``fn(stages, ring, cfg) -> dict`` hook); :func:`accounting` merges those of a run's
kinds, upstream first. ``stages`` is every stage's stats by name (each with its
``kind``), ``ring`` the ring's own stats (None without a ring). docs/architecture.md
("Accounting") and docs/reliability.md say what each identity means.

Also here: which stats are running totals (:func:`merge_counts`, summed over a stage's
restarts) and the read-back of what a killed ingest wrote but never reported
(:func:`reconcile_ring_writer`).
"""
from __future__ import annotations

import logging
from typing import Any

from ..stage.kinds import StageKind, resolve, stage_kinds

log = logging.getLogger("pointflow.supervisor")

#: Running totals of every stage; each kind adds its own (:attr:`StageKind.counters`).
BASE_COUNTERS = ("points_in", "points_out")
#: Per-reason maps, merged key by key over restarts.
COUNTER_MAPS = ("drops", "rejected", "skipped")
#: The kind that writes the ring: its counts are checked against the ring's own.
RING_WRITER = "ingest"


def counter_names() -> frozenset[str]:
    """Stats that are running totals (carried over a restart) wherever they appear: the
    base ones and every registered kind's; everything else is a gauge and shows the
    current incarnation's value."""
    names = set(BASE_COUNTERS)
    for k in stage_kinds().values():
        names.update(k.counters)
    return frozenset(names)


def merge_counts(a: dict, b: dict, counters: frozenset[str] | None = None) -> dict:
    """Totals of two incarnations' stats: counters added, per-reason maps merged."""
    out = dict(b)
    for k in counters if counters is not None else counter_names():
        va, vb = a.get(k, 0), b.get(k, 0)
        if isinstance(va, (int, float)) and isinstance(vb, (int, float)) and (k in a or k in b):
            out[k] = va + vb
    for k in COUNTER_MAPS:
        if isinstance(a.get(k), dict) or isinstance(b.get(k), dict):
            m = dict(a.get(k) or {})
            for r, n in (b.get(k) or {}).items():
                m[r] = m.get(r, 0) + n if isinstance(n, (int, float)) else n
            out[k] = m
    return out


def accounting(kinds: list[StageKind], stages: dict, ring: dict | None, cfg) -> dict[str, Any]:
    """The identities of a run's kinds, upstream first (empty when none has any)."""
    acc: dict[str, Any] = {}
    for k in sorted(kinds, key=lambda k: -k.start_order):
        if k.accounting:
            acc.update(resolve(k.accounting)(stages, ring, cfg))
    return acc


def reconcile_ring_writer(st, ring) -> None:
    """Points an ingest wrote after its last heartbeat (killed, or its last report lost)
    are in the ring but not in its counters. The ring's own write count (in shared
    memory, updated under the ring's lock in the same step as the write) is the truth:
    add the difference to the counts (received and written) and report it as
    ``unreported_written``. Runs when ingest dies and once more after the stop.
    ``st`` is the supervisor's record of the ingest stage."""
    if ring is None:
        return
    try:
        # without the ring's lock: a stage stopped inside a push (frozen, starved) must
        # not stop supervision; the writer is gone, so the counter is final
        written = int(ring.stats(wait=False).total_written)
    except Exception:  # noqa: BLE001
        return
    st.ring_at_report = written  # both sides as of now: ingest's totals are set from it
    reported = int(st.carried.get("points_out", 0)) + int(st.stats.get("points_out", 0))
    if written > reported:
        st.stats = dict(st.stats)
        for k in ("points_in", "points_out", "unreported_written"):
            st.stats[k] = int(st.stats.get(k, 0)) + (written - reported)
        log.info("ingest: %d points written after its last report added to its counts", written - reported)


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


def _sources(stages: dict) -> list[dict]:
    return [v for v in stages.values() if v.get("kind") == "source"]


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
    sources = _sources(stages)
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


def send_identities(stages: dict, ring: dict | None, cfg) -> dict[str, Any]:
    """``pointflow send``: points the sources produced = handed to the link + dropped."""
    snd = stages.get("sender", {})
    sources = _sources(stages)
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
