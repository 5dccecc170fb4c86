"""The ``ring:`` section and the one builder that turns it into a ring and its slabs.

Everything that makes a ring from a config goes through here: the supervisor of a run,
``pointflow validate``'s space check, the one-stage test rig and the benchmarks. So the
rules live once: the layout (:func:`ring_layout`), the shared-memory space check
(:func:`check_ring_space`), the ring and slabs (:func:`build_ring`), and the importance
rule (:func:`importance_slot`, :func:`importance_values`): a config that ranks points
(``importance_field``, or ``eviction: importance``) gets the ring's own ``importance``
array, which ingest fills per chunk from the configured field.

``channels`` is what the whole config uses (``PipelineConfig.ring_channels()``: the render
colour, the importance field, extras, the recording's, ``source_index``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, NamedTuple, Optional, Sequence

from ..typed import ConfigError, at_least_one, check, non_negative

#: The ring's own importance values (a slot array, not a channel of the data), written by
#: ingest from the configured ``importance_field``.
IMPORTANCE_SLOT = "importance"


@dataclass
class RingConfig:
    max_points: int = field(default=1_000_000, metadata=check(at_least_one))
    eviction: Literal["drop_oldest", "drop_newest", "importance"] = "drop_oldest"
    #: A channel name, ``auto`` (intensity if present, else the first channel), or none.
    importance_field: Optional[str] = None
    max_staleness_ms: float = field(default=0.0, metadata=check(non_negative))
    classification_weights: Optional[dict[int, float]] = None
    #: Extra channels to keep beyond those the render config uses.
    extra_channels: list[str] = field(default_factory=list)


def check_ring(ring: RingConfig) -> None:
    """Relations between the section's values (single bounds are on the fields): eviction
    by importance without a field or weights ranks by ``auto``."""
    if ring.eviction == "importance" and not ring.importance_field and not ring.classification_weights:
        ring.importance_field = "auto"


def importance_slot(ring: RingConfig) -> Optional[str]:
    """The ring's importance array name when the config ranks points, else None."""
    return IMPORTANCE_SLOT if (ring.importance_field or ring.eviction == "importance") else None


def importance_values(field_name: Optional[str], channels: dict):
    """A chunk's importance per point from the configured field (``auto``: intensity if
    the chunk has it, else its first one-wide channel), as float32; None without one."""
    import numpy as np

    f = field_name
    if not f:
        return None
    if f == "auto":
        if "intensity" in channels:
            f = "intensity"
        else:
            f = next((k for k, v in channels.items() if v.ndim == 1 or v.shape[1] == 1), None)
            if f is None:
                return None
    arr = channels.get(f)
    if arr is None or (arr.ndim == 2 and arr.shape[1] != 1):
        return None
    return np.asarray(arr, dtype=np.float32).reshape(-1)


def ring_layout(ring: RingConfig, channels: Sequence[str]):
    """The ring's layout for ``ring.max_points`` points of ``channels``."""
    from .layout import RingLayout, as_channel_specs

    return RingLayout(ring.max_points, as_channel_specs(channels))


def check_ring_space(ring: RingConfig, channels: Sequence[str], note: str = "") -> int:
    """The bytes the ring and its two slabs need; ConfigError naming ``ring.max_points``
    (with ``note`` appended) when they do not fit in shared memory. Creates nothing."""
    from .space import RingSpaceError, check_shm_space

    try:
        return check_shm_space(ring_layout(ring, channels))
    except RingSpaceError as exc:
        raise ConfigError("ring.max_points", f"{exc}{note}") from None


class BuiltRing(NamedTuple):
    ring: "PointRing"  # noqa: F821 - imported lazily
    slabs: "SlabPair"  # noqa: F821


def build_ring(ring: RingConfig, channels: Sequence[str], *, check_space: bool = True) -> BuiltRing:
    """Create the ring and its two slabs from the ``ring:`` section (the caller closes and
    unlinks both). Checks the space first unless the caller did (``check_space=False``);
    a failure to allocate is a ConfigError naming ``ring.max_points``, nothing left behind."""
    from .ring import PointRing
    from .slabs import SlabPair
    from .space import shm_bytes

    if check_space:
        check_ring_space(ring, channels)
    pr = None
    try:
        pr = PointRing(ring.max_points, channels=list(channels), eviction=ring.eviction,
                       importance_field=importance_slot(ring), max_staleness_ms=ring.max_staleness_ms,
                       classification_weights=ring.classification_weights)
        slabs = SlabPair.create(pr.layout)
    except OSError as exc:  # space taken since the check, or a memory limit
        if pr is not None:
            pr.close()
            pr.unlink()
        raise ConfigError("ring.max_points", f"cannot allocate the ring and slabs "
                                             f"({shm_bytes(ring_layout(ring, channels)):,} bytes) "
                                             f"in shared memory: {exc.strerror or exc}") from None
    return BuiltRing(pr, slabs)
