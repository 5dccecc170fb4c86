"""The stage kit: what every stage imports, below every stage.

* :mod:`.kinds`: what a stage kind is (:class:`StageKind`, :func:`register_stage_kind`,
  :func:`stage_kind`, :func:`stage_kinds`), one record per kind, declared next to its code;
* :mod:`.context`: what a stage process holds (:class:`StageContext`: heartbeats, counters,
  spans, stop; :class:`RunInfo`, what the supervisor hands it) and the socket helpers;
* :mod:`.accounting`: the pieces the stages' accounting identities share;
* :mod:`.console`: log lines on a terminal that hold a progress line.

What runs the stages (the supervisor, the launch of a stage process, :class:`Pipeline`)
is :mod:`pointflow.runtime`, above the stages.
"""
from .._lazy import lazy_exports

__getattr__ = lazy_exports(__name__, {
    "StageContext": ".context", "RunInfo": ".context", "StageCounters": ".context",
    "StageKind": ".kinds", "register_stage_kind": ".kinds", "stage_kind": ".kinds", "stage_kinds": ".kinds",
})

__all__ = ["RunInfo", "StageContext", "StageCounters", "StageKind", "register_stage_kind", "stage_kind",
           "stage_kinds"]
