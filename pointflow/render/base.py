"""What a render tier receives and must provide.

A tier draws the ring's occupied slots (slot s is occupied iff ``(s - head) % capacity
< size``) from a :class:`FrameInput` — views on a shared-memory slab in slot order — with
a :class:`~pointflow.render.camera.Camera`. Rasterisation rules shared by all tiers:
a square point of size s px centred at (px, py) covers the pixels whose centres lie in
[px - s/2, px + s/2) x [py - s/2, py + s/2); a round point covers those whose centre is
within s/2 of (px, py) (``<=``); nearer depth wins, ties go to the lower logical index.
World-size points are converted to pixels and clamped to [1, 4096] px. The LOD stride
keeps logical indices divisible by it. Importance sampling keeps a point when
``pcg_hash(slot, seed) / 2**32 <= p`` with p the importance normalised over its range
(p = 1 for a degenerate range); a budget b below the survivors n thins them by
``max(b - 3*sqrt(b), b/2) / n`` and then keeps at most b. The auto colour range is taken
over occupied slots with finite positions. Reference implementation: ``rules.py``.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar, Optional

import numpy as np

from ..errors import Error
from .camera import Camera
from .config import RenderConfig

#: A half-open range of ring slots.
Range = tuple[int, int]


def merge_ranges(ranges: list[Range], capacity: int) -> list[Range]:
    """A frame's dirty slot ranges as a tier uploads them: sorted, non-overlapping, clipped
    to [0, capacity); a wrapping range (b < a) is split."""
    out: list[Range] = []
    for a, b in ranges:
        a, b = int(a), int(b)
        if b < a:  # wraps around the end of the ring
            out.extend([(a, capacity), (0, b)])
        else:
            out.append((a, b))
    out = sorted((max(a, 0), min(b, capacity)) for a, b in out if min(b, capacity) > max(a, 0))
    merged: list[Range] = []
    for a, b in out:
        if merged and a <= merged[-1][1]:
            merged[-1] = (merged[-1][0], max(merged[-1][1], b))
        else:
            merged.append((a, b))
    return merged


@dataclass
class FrameInput:
    positions: np.ndarray           # (capacity, 3) float32 offsets from ``origin``, slot order
    importance: np.ndarray          # (capacity,) float32
    t_ingest_ms: np.ndarray         # (capacity,) ingest time, ms since the ring epoch
    channels: dict[str, np.ndarray]  # (capacity,) float32 scalars; ``rgb`` (capacity, 3) uint8
    head: int
    size: int
    capacity: int
    origin: np.ndarray              # (3,) float64
    now_ms: float                   # ms since the ring epoch, for the time window
    channel_ranges: dict[str, tuple[float, float]] = field(default_factory=dict)
    dirty: Optional[list[tuple[int, int]]] = None  # None = everything changed
    budget: Optional[int] = None    # point budget from the policy engine
    seq: int = 0
    frame_seed: int = 0
    #: With a map (render/maplayer.py): slots [0, live_slots) are the ring's, and ``map_box`` is
    #: the map's (lo, hi) in world float64, so the camera frames and clips each (tiers ignore both).
    live_slots: Optional[int] = None
    map_box: Optional[tuple] = None

    def occupied_slots(self) -> np.ndarray:
        """Slot indices in logical order (oldest first)."""
        return (self.head + np.arange(self.size, dtype=np.int64)) % max(self.capacity, 1)


@dataclass
class FrameStats:
    drawn: Optional[int] = None     # points drawn (None when not known without a readback)
    timings_ms: dict[str, float] = field(default_factory=dict)
    uploaded_bytes: int = 0
    extra: dict[str, Any] = field(default_factory=dict)


class RenderError(Error, RuntimeError):
    """A tier could not start or lost its device; the selector falls back."""


class Renderer(ABC):
    tier: ClassVar[str] = ""
    #: True when the tier keeps its own copy of the ring (uploaded by dirty ranges): it can
    #: draw again with ``frame.dirty == []`` after the slab went back (render/view/hub.py).
    keeps_data: ClassVar[bool] = False

    def __init__(self, cfg: RenderConfig, capacity: int, channels: list[str]):
        self.cfg = cfg
        self.capacity = capacity
        self.channels = channels
        self.width, self.height = cfg.size

    @abstractmethod
    def render(self, frame: FrameInput, camera: Camera) -> FrameStats:
        """Draw one frame into the tier's target."""

    @abstractmethod
    def read_image(self) -> np.ndarray:
        """(height, width, 4) uint8 RGBA of the last frame."""

    def pick(self, x: float, y: float, pixel_ratio: float = 1.0) -> Optional[int]:
        """Ring slot of the point under window pixel (x, y), or None."""
        raise NotImplementedError(f"{self.tier} tier does not support picking")

    def restyle(self, cfg: RenderConfig) -> bool:
        """Take a new style (colouring, point size and shape, EDL, time window) for the next
        frame, in place; False when the tier cannot (it caches them in pipelines), and the
        render stage builds a new renderer of the same tier instead (render/view/protocol.py)."""
        return False

    def resize(self, width: int, height: int) -> bool:
        """Draw the next frames at ``width`` x ``height`` (a view of another size,
        render/view/hub.py); False when the tier cannot (the view then gets the tier's size).
        Tiers that can keep one target per size, so switching back costs nothing."""
        return (int(width), int(height)) == (self.width, self.height)

    def forget_sizes(self, keep) -> int:
        """Free the targets :meth:`resize` kept for sizes not in ``keep`` (the current size
        always stays): a view closed or resized must not leave its target behind
        (render/view/hub.py bounds them). Returns how many were freed."""
        targets = self.__dict__.get("_targets")
        if not targets:
            return 0
        keep = {tuple(k) for k in keep} | {(self.width, self.height)}
        gone = [s for s in targets if s not in keep]
        for size in gone:
            for obj in targets.pop(size):
                _free(obj)
        return len(gone)

    def info(self) -> dict[str, Any]:
        return {"tier": self.tier}

    def close(self) -> None:
        pass


def _free(obj: Any) -> None:
    """Release one part of a dropped target: a GPU buffer or method (``destroy`` /
    ``release`` / ``close``); host arrays just lose their last reference."""
    for name in ("close", "release", "destroy"):
        f = getattr(obj, name, None)
        if callable(f) and not isinstance(obj, np.ndarray):
            try:
                f()
            except Exception:  # noqa: BLE001 - already freed, or the device is gone
                pass
            return
