"""The map drawn while its index is built: the build's first pass hands over an evenly spread
share of each chunk it reads (``open_map(preview=...)``), and the map stage places those points
in the map region as they come, a version at a time, so a first open of a big file draws a
coarse map within a chunk's read instead of after the whole build. Once the map is open the
stage's :class:`~pointflow.map.process.Server` takes the region over: its first version is a
full one (the render stage drops the preview), and the preview's slots are its to reuse once
the render stage has acknowledged that version."""
from __future__ import annotations

import threading
from collections import deque
from typing import Optional

import numpy as np
import zmq

from ..arrays import rgb_u8
from ..render import mapregion as mr


class Preview:
    """Preview points, offered by the opener thread, placed and published by the stage loop."""

    def __init__(self, ctx, budget: int, channels_for, bounds, files: list[str], push, units=None):
        self.ctx, self.budget, self.channels_for = ctx, int(budget), channels_for
        self.files, self.push = files, push
        self.bounds = bounds  # (lo, hi) from the headers, or None
        self.units = units  # {"xy", "z"} from the headers' CRS, or None
        self.queue: deque = deque()
        self.lock = threading.Lock()
        self.offered = 0  # points taken into the queue (at most the budget)
        self.region: Optional[mr.MapRegion] = None
        self.used = 0  # slots [0, used) hold preview points
        self.version = 0
        self.full_next = True
        self.origin: Optional[np.ndarray] = None
        self.ranges: dict[str, list[float]] = {}

    def offer(self, file_index: int, data: dict) -> None:
        """From the opener thread: a decoded share of a chunk (dropped once the budget is full)."""
        n = int(len(data["positions"]))
        with self.lock:
            room = self.budget - self.offered
            if room <= 0 or not n:
                return
            if n > room:
                data = {k: v[:room] for k, v in data.items()}
                n = room
            self.offered += n
            self.queue.append((file_index, data))

    def step(self) -> None:
        """Place what was offered; publish a version when anything was placed (or a render stage
        that said hello needs everything again)."""
        set_r = []
        while self.queue:
            fi, data = self.queue.popleft()
            if self.region is None:
                chans = self.channels_for([k for k in data if k != "positions"])
                self.region = mr.MapRegion.create(self.ctx.info.run_dir, self.budget, chans)
            pos = np.asarray(data["positions"], np.float64)
            if self.origin is None:
                lo, hi = self.bounds if self.bounds is not None else (pos.min(axis=0), pos.max(axis=0))
                self.origin = np.round((np.asarray(lo) + np.asarray(hi)) / 2.0, 3)
            a, b = self.used, self.used + pos.shape[0]
            r = self.region
            r.positions[a:b] = pos
            r.file[a:b] = fi
            for name, arr in r.channel.items():
                v = data.get(name)
                if v is None:
                    arr[a:b] = 0 if arr.dtype.kind == "u" else np.nan
                    continue
                v = np.asarray(v)
                if name == "rgb" and v.dtype.itemsize > 1:  # 16-bit LAS colour, as the ring takes it
                    v = rgb_u8(v)  # (0..255 kept: many LAS files use only that range)
                arr[a:b] = v.reshape(arr[a:b].shape).astype(arr.dtype, copy=False)
                if arr.ndim == 1 and b > a:
                    fv = np.asarray(arr[a:b], np.float64)
                    fv = fv[np.isfinite(fv)]
                    if fv.size:
                        cur = self.ranges.get(name)
                        lo_, hi_ = float(fv.min()), float(fv.max())
                        self.ranges[name] = [lo_, hi_] if cur is None else [min(cur[0], lo_), max(cur[1], hi_)]
            self.used = b
            set_r.append((a, b))
        if self.region is None or not (set_r or self.full_next):
            return
        self.version += 1
        full = self.full_next
        msg = {"type": "version", "version": self.version, "full": full, "region": self.region.path,
               "slots": self.region.slots, "channels": [list(c) for c in self.region.channels], "files": self.files,
               "origin": [float(v) for v in self.origin],
               "set": ([(0, self.used)] if self.used else []) if full else set_r, "cleared": [],
               "points": self.used, "nodes": 0, "channel_ranges": self.ranges, "preview": True}
        if self.bounds is not None:
            msg["bounds"] = [np.asarray(self.bounds[0]).tolist(), np.asarray(self.bounds[1]).tolist()]
            msg["units"] = self.units
        try:
            self.push.send(mr.encode(msg), zmq.NOBLOCK)
            self.full_next = False
        except zmq.Again:  # no render stage yet: everything again with the next step
            self.version -= 1
            self.full_next = True
        c = self.ctx.counters
        c.extra.update(map_points=self.used, map_preview_points=self.used, map_version=self.version)

    def clear(self) -> None:
        """The map could not be opened after all: the render stage drops what the preview showed."""
        with self.lock:
            self.queue.clear()
            self.offered = self.budget  # nothing more is taken
        self.bounds = None  # the views stop framing it (the stage said so; no version says otherwise)
        if self.region is not None and self.used:
            self.used, self.ranges = 0, {}
            self.full_next = True
            self.step()

    def held(self) -> np.ndarray:
        """The slots the preview holds (the server frees them once its full version is acknowledged)."""
        return np.arange(self.used, dtype=np.int32)
