"""A transport that emits a growing helix: the smallest useful plugin.

A plugin is a :class:`pointflow.ingest.transports.Transport` subclass with a ``name``, an
``options_schema`` dataclass (validated when the YAML is loaded; errors name the key), and
``chunks()``, a generator of :class:`pointflow.chunk.PointChunk` (or ``None`` when idle).
"""
from __future__ import annotations

import dataclasses
import time
from typing import Iterator, Optional

import numpy as np

from pointflow.chunk import PointChunk
from pointflow.typed import ConfigError
from pointflow.ingest.transports import Transport


@dataclasses.dataclass
class HelixOptions:
    points_per_chunk: int = 1000
    #: Stop after this many chunks (0 = forever).
    chunks: int = 0
    radius: float = 10.0
    turns: float = 5.0
    #: Chunks per second (0 = as fast as possible).
    rate: float = 20.0


class HelixTransport(Transport):
    name = "helix"
    options_schema = HelixOptions

    @classmethod
    def check_options(cls, o: HelixOptions, path: str, base_dir: str) -> None:
        if o.points_per_chunk < 1:
            raise ConfigError(f"{path}.points_per_chunk", f"must be >= 1, got {o.points_per_chunk}")
        if o.radius <= 0:
            raise ConfigError(f"{path}.radius", f"must be > 0, got {o.radius}")

    def chunks(self) -> Iterator[Optional[PointChunk]]:
        o = self.opts
        k = 0
        t0 = time.monotonic()
        while o.chunks == 0 or k < o.chunks:
            if o.rate > 0:
                while time.monotonic() < t0 + k / o.rate:
                    time.sleep(0.01)
                    yield None
            s = (k * o.points_per_chunk + np.arange(o.points_per_chunk)) / 2000.0
            ang = s * 2 * np.pi * o.turns / 10
            pos = np.column_stack([o.radius * np.cos(ang), o.radius * np.sin(ang), s])
            yield PointChunk(positions=pos, channels={"intensity": (s % 1.0 * 255).astype(np.float32)},
                             source_id=self.source_id)
            k += 1
