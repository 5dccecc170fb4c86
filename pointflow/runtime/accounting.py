"""Where every point went: ``stats()["accounting"]`` of a run.

Each stage kind names the identities its counters enter (:attr:`StageKind.accounting`,
a ``fn(stages, ring, cfg) -> dict`` hook, beside the stage: ``ingest/accounting.py``,
``record/accounting.py``, ``remote/accounting.py``, ``map/process.py``); :func:`accounting`
merges those of a run's kinds, upstream first. ``stages`` is every stage's stats by name
(each with its ``kind``), ``ring`` the ring's own stats (None without a ring).
docs/architecture.md ("Accounting") and docs/reliability.md say what each identity means.

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
