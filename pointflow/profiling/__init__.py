"""Where the time goes: trace spans from every stage, collected and reported
(docs/profiling.md).

* :mod:`.spans`: :class:`~.spans.SpanEmitter`, what a stage records and sends in batches;
* :mod:`.collector`: :class:`~.collector.SpanCollector`, the supervisor's bounded store;
* :mod:`.report`: :func:`~.report.build_profile` and :func:`~.report.write_profile`
  (per-stage latency, ``trace.json`` for Perfetto, ``latency.png``).
"""
from .._lazy import lazy_exports

__getattr__ = lazy_exports(__name__, {
    "SpanEmitter": ".spans", "SpanCollector": ".collector", "build_profile": ".report", "write_profile": ".report",
})

__all__ = ["SpanCollector", "SpanEmitter", "build_profile", "write_profile"]
