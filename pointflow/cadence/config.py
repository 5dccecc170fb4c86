"""The ``cadence:`` and ``policy:`` sections (the loader, pointflow/config.py, assembles
them; :mod:`.policy` turns them into a point budget and an update cadence)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Optional

from ..stage.endpoints import Endpoint
from ..typed import at_least_one, check, non_negative, positive


#: The cadence's links with render: the frames it hands on and the slabs render gives back.
ENDPOINTS = (Endpoint("frames", "frames", "cadence -> render: frame messages"),
             Endpoint("release", "release", "render -> cadence: slabs released, hello and frame reports"))


@dataclass
class PolicyConfig:
    tier: Literal["auto", "L", "M", "H"] = "auto"
    mode: Literal["eco", "balanced", "max_throughput", "custom"] = "balanced"
    point_budget_cap: Optional[int] = field(default=None, metadata=check(at_least_one))
    update_cadence_min_ms: Optional[float] = field(default=None, metadata=check(non_negative))
    legacy: bool = False
    #: The view cap: budget <= this multiple of the viewport's pixel count.
    points_per_pixel: float = field(default=4.0, metadata=check(positive))


@dataclass
class CadenceConfig:
    target_hz: float = field(default=60.0, metadata=check(positive))
    adaptive: bool = False
    #: Hand over a new snapshot only once the renderer has finished the last one, so a slow
    #: renderer always draws the newest data instead of one queued a frame ago.
    latest_only: bool = True
