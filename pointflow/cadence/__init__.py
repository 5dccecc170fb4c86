"""The cadence stage: snapshot the ring at a steady rate and hand slabs to the renderer.

* :mod:`.process`: the stage and :class:`Cadence` (one tick: copy what changed into the
  free slab, hand it over);
* :mod:`.ticker`: :class:`~.ticker.Ticker`, absolute deadlines with an injectable clock;
* :mod:`.policy`: :func:`~.policy.resolve_policy`, the point budget and update cadence
  from the hardware tier and the config;
* :mod:`.prefill`: copying the ring's changes while the renderer still draws;
* :mod:`.messages`: the render → cadence control messages (hello, frame time, idle).
"""
from .._lazy import lazy_exports

__getattr__ = lazy_exports(__name__, {
    "Cadence": ".process", "Ticker": ".ticker", "resolve_policy": ".policy", "PolicyDecision": ".policy",
})

__all__ = ["Cadence", "PolicyDecision", "Ticker", "resolve_policy"]
