"""The map region: where the map stage puts the points it selected, for the render stage.

A file in the run directory, mapped by both stages (shared memory that the supervisor's
run-directory cleanup removes however a run ends): ``slots`` = ``map.point_budget`` slots of
float64 world positions, the file index of each point, and the kept channels (float32
scalars, ``rgb`` uint8 x 3). The map stage writes only slots that no published version holds
(free, or cleared in a version the render stage has acknowledged), then sends a version
message naming the slot ranges it set and cleared; the render stage copies those ranges when
the message arrives (converting positions to float32 offsets from its origin in float64) and
acknowledges. So neither side ever reads a slot while the other writes it, and a frame never
waits for the map stage.

Messages (one JSON frame each):

* map -> render, ``endpoints.map`` (PUSH -> PULL bound by render): ``{"type": "version",
  "version", "full", "region", "slots", "channels": [[name, dtype, width], ...], "files",
  "origin", "set": [[a, b], ...], "cleared": [[a, b], ...], "points", "nodes",
  "channel_ranges": {name: [lo, hi]}}``. ``full`` (the first message of a map stage, and the
  answer to a ``hello``): every slot not in ``set`` is empty.
* render -> map, ``endpoints.map_camera`` (PUSH -> PULL bound by the map stage):
  ``{"type": "cameras", "views": [{"view", "eye", "target", "up", "fov_deg", "near", "far",
  "width", "height"}, ...]}`` (the main view first), ``{"type": "ack", "version"}``,
  ``{"type": "hello"}`` (a render stage started: send everything again).
"""
from __future__ import annotations

import json
import mmap
import os
from typing import Optional

import numpy as np

MAP_TAG = "pf.map/1"
_ALIGN = 64


def channel_spec(name: str) -> tuple[str, str, int]:
    """(name, dtype, width) of a kept channel: the ring's convention (rgb uint8 x 3, others float32)."""
    return (name, "uint8", 3) if name == "rgb" else (name, "float32", 1)


def _layout(slots: int, channels: list) -> tuple[list[tuple[str, np.dtype, tuple]], int]:
    specs = [("positions", np.dtype(np.float64), (slots, 3)), ("file", np.dtype(np.uint16), (slots,))]
    for name, dt, width in channels:
        specs.append(("ch:" + name, np.dtype(dt), (slots,) if int(width) == 1 else (slots, int(width))))
    out, off = [], 0
    for key, dt, shape in specs:
        out.append((key, dt, shape, off))
        off += (int(np.prod(shape)) * dt.itemsize + _ALIGN - 1) // _ALIGN * _ALIGN
    return out, max(off, _ALIGN)


class MapRegion:
    """numpy views of a map region file (see the module docstring)."""

    def __init__(self, path: str, slots: int, channels: list, *, create: bool):
        self.path, self.slots = path, int(slots)
        self.channels = [tuple(c) for c in channels]
        specs, size = _layout(self.slots, self.channels)
        flags = os.O_RDWR | (os.O_CREAT | os.O_EXCL if create else 0)
        fd = os.open(path, flags, 0o600)
        try:
            if create:
                os.ftruncate(fd, size)
            elif os.fstat(fd).st_size < size:
                raise ValueError(f"map region {path}: {os.fstat(fd).st_size} bytes, expected {size}")
            self._mm = mmap.mmap(fd, size)
        finally:
            os.close(fd)
        self.arrays = {key: np.ndarray(shape, dt, buffer=self._mm, offset=off) for key, dt, shape, off in specs}
        self.positions = self.arrays["positions"]
        self.file = self.arrays["file"]
        self.channel = {k[3:]: v for k, v in self.arrays.items() if k.startswith("ch:")}

    @classmethod
    def create(cls, run_dir: str, slots: int, channels: list) -> "MapRegion":
        path = os.path.join(run_dir, f"map-region-{os.getpid()}-{os.urandom(4).hex()}")
        return cls(path, slots, channels, create=True)

    @classmethod
    def attach(cls, path: str, slots: int, channels: list) -> "MapRegion":
        return cls(path, slots, channels, create=False)

    def close(self) -> None:
        self.arrays.clear()
        self.positions = self.file = None  # type: ignore[assignment]
        self.channel = {}
        try:
            self._mm.close()
        except BufferError:  # a view is still alive somewhere; the mapping goes with the process
            pass

    def unlink(self) -> None:
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass


def runs(slots: np.ndarray) -> list[tuple[int, int]]:
    """Half-open ranges of consecutive values of sorted int ``slots``."""
    s = np.asarray(slots, np.int64)
    if not s.size:
        return []
    cut = np.flatnonzero(np.diff(s) != 1) + 1
    starts = np.concatenate([[0], cut])
    ends = np.concatenate([cut, [s.size]])
    return [(int(s[a]), int(s[b - 1]) + 1) for a, b in zip(starts, ends)]


def encode(msg: dict) -> bytes:
    return json.dumps({"tag": MAP_TAG, **msg}, separators=(",", ":")).encode()


def decode(raw: bytes) -> Optional[dict]:
    """The message, or None when it is not one of ours."""
    try:
        msg = json.loads(raw)
    except ValueError:
        return None
    return msg if isinstance(msg, dict) and msg.get("tag") == MAP_TAG else None


def camera_dict(view: str, camera, width: int, height: int) -> dict:
    return {"view": view, "eye": [float(v) for v in camera.eye], "target": [float(v) for v in camera.target],
            "up": [float(v) for v in camera.up], "fov_deg": float(camera.fov_deg), "near": float(camera.near),
            "far": float(camera.far), "width": int(width), "height": int(height)}


def map_slots(cfg) -> int:
    """Extra slots the render stage draws after the ring's (0 without a map): the map's
    ``point_budget``; ``cfg`` is the run's PipelineConfig."""
    mc = getattr(cfg, "map", None)
    return int(mc.point_budget) if mc is not None else 0
