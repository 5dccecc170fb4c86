"""JSON point chunks, as web services and scripts send them (websocket, SSE, ZeroMQ).

Two shapes are accepted, both as one JSON object:

* point list: ``{"points": [{"x": 1, "y": 2, "z": 3, "attributes": {"intensity": 7}}, ...]}``
  (attributes may also sit next to x/y/z);
* columnar: ``{"x": [...], "y": [...], "z": [...], "channels": {"intensity": [...]}}`` or
  ``{"positions": [[x, y, z], ...], "channels": {...}}`` (``attributes`` is a synonym of
  ``channels``).

Optional keys: ``source``, ``seq``. Every defect raises :class:`ChunkError` with a reason:
``bad_json`` (not JSON / not UTF-8), ``bad_shape`` (JSON of the wrong shape),
``bad_dtype`` (non-numeric values), ``length_mismatch``, ``too_large``.
The point-list form necessarily walks Python objects per point (that is what JSON decoding
produces); the columnar form goes straight to numpy.
"""
from __future__ import annotations

import json
import time
from typing import Any

import numpy as np

from ..chunk import ChunkError, PointChunk

#: Channels whose values are not scalars: name -> width.
_VECTOR_CHANNELS = {"rgb": 3}


def _num_array(values: Any, what: str, dtype=np.float64) -> np.ndarray:
    if not isinstance(values, list):
        raise ChunkError("bad_shape", f"{what} must be a list, got {type(values).__name__}")
    try:
        arr = np.array(values, dtype=dtype)
    except (TypeError, ValueError, OverflowError):
        raise ChunkError("bad_dtype", f"{what} must hold numbers only") from None
    return arr


def _channel_dtype(name: str, arr: np.ndarray) -> np.ndarray:
    if name == "rgb":
        if arr.size and float(np.nanmax(arr)) <= 1.0 and arr.dtype.kind == "f":
            arr = arr * 255.0
        return np.clip(np.nan_to_num(arr), 0, 65535).astype(np.uint16 if arr.size and arr.max() > 255 else np.uint8)
    return arr.astype(np.float32) if arr.dtype == np.float64 else arr


def parse_json_chunk(data: bytes | bytearray | memoryview | str | dict, max_points: int | None = None,
                     source_id: str = "") -> PointChunk:
    """Parse one JSON chunk (bytes, text or an already decoded object)."""
    if isinstance(data, dict):
        obj = data
    else:
        try:
            text = bytes(data).decode("utf-8") if not isinstance(data, str) else data
            obj = json.loads(text)
        except (UnicodeDecodeError, ValueError) as exc:
            raise ChunkError("bad_json", f"not valid JSON: {str(exc)[:120]}") from None
    if not isinstance(obj, dict):
        raise ChunkError("bad_shape", f"a JSON chunk must be an object, got {type(obj).__name__}")
    if "points" in obj:
        pos, chans = _from_point_list(obj["points"], max_points)
    elif "positions" in obj or "x" in obj:
        pos, chans = _from_columns(obj, max_points)
    else:
        raise ChunkError("bad_shape", "a JSON chunk needs 'points' (list of {x,y,z}) or columns ('x','y','z' or 'positions')")
    src = obj.get("source", source_id)
    seq = obj.get("seq", 0)
    return PointChunk(positions=pos, channels=chans, source_id=src if isinstance(src, str) else source_id,
                      seq=seq if isinstance(seq, int) and not isinstance(seq, bool) else 0,
                      t_recv_ns=time.monotonic_ns())


def _check_count(n: int, max_points: int | None) -> None:
    if max_points is not None and n > max_points:
        raise ChunkError("too_large", f"chunk has {n} points, more than the configured maximum {max_points}")


def _from_point_list(points: Any, max_points: int | None):
    if not isinstance(points, list):
        raise ChunkError("bad_shape", f"'points' must be a list, got {type(points).__name__}")
    n = len(points)
    _check_count(n, max_points)
    if not all(isinstance(p, dict) for p in points):
        raise ChunkError("bad_shape", "every entry of 'points' must be an object with x, y, z")
    try:
        xyz = [(p["x"], p["y"], p["z"]) for p in points]
    except KeyError as exc:
        raise ChunkError("bad_shape", f"a point is missing {exc.args[0]!r}") from None
    pos = _num_array(xyz, "points[].x/y/z").reshape(n, 3)
    # attribute names: union over points; every point must carry every attribute
    names: dict[str, None] = {}
    for p in points[:1]:
        attrs = p.get("attributes", {})
        if not isinstance(attrs, dict):
            raise ChunkError("bad_shape", "'attributes' must be an object")
        names.update(dict.fromkeys(attrs))
        names.update(dict.fromkeys(k for k in p if k not in ("x", "y", "z", "attributes")))
    chans: dict[str, np.ndarray] = {}
    for name in names:
        try:
            vals = [p["attributes"][name] if name in p.get("attributes", ()) else p[name] for p in points]
        except (KeyError, TypeError):
            raise ChunkError("length_mismatch", f"attribute {name!r} is missing on some points") from None
        arr = _num_array(vals, f"attribute {name!r}")
        if arr.ndim != 1 and not (arr.ndim == 2 and name in _VECTOR_CHANNELS):
            raise ChunkError("bad_shape", f"attribute {name!r} must be a number per point")
        chans[name] = _channel_dtype(name, arr)
    return pos, chans


def _from_columns(obj: dict, max_points: int | None):
    if "positions" in obj:
        pos = _num_array(obj["positions"], "'positions'")
        if pos.size == 0:
            pos = pos.reshape(0, 3)
        if pos.ndim != 2 or pos.shape[1] != 3:
            raise ChunkError("bad_shape", f"'positions' must be a list of [x, y, z], got shape {pos.shape}")
    else:
        cols = []
        for k in ("x", "y", "z"):
            if k not in obj:
                raise ChunkError("bad_shape", f"columnar chunk is missing {k!r}")
            c = _num_array(obj[k], repr(k))
            if c.ndim != 1:
                raise ChunkError("bad_shape", f"column {k!r} must be a flat list of numbers")
            cols.append(c)
        if not (len(cols[0]) == len(cols[1]) == len(cols[2])):
            raise ChunkError("length_mismatch", f"columns x, y, z have lengths {[len(c) for c in cols]}")
        pos = np.column_stack(cols) if cols[0].size else np.zeros((0, 3))
    n = pos.shape[0]
    _check_count(n, max_points)
    raw = obj.get("channels", obj.get("attributes", {}))
    if not isinstance(raw, dict):
        raise ChunkError("bad_shape", "'channels' must be an object of name -> list")
    chans: dict[str, np.ndarray] = {}
    for name, vals in raw.items():
        arr = _num_array(vals, f"channel {name!r}")
        if arr.shape[:1] != (n,):
            raise ChunkError("length_mismatch", f"channel {name!r} has {arr.shape[0] if arr.ndim else 0} values for {n} points")
        if arr.ndim != 1 and not (arr.ndim == 2 and name in _VECTOR_CHANNELS):
            raise ChunkError("bad_shape", f"channel {name!r} must be a number per point")
        chans[str(name)] = _channel_dtype(name, arr)
    return pos, chans


def chunk_to_json(chunk: PointChunk, columnar: bool = True) -> str:
    """The JSON form of a chunk (tests, examples, other-language senders)."""
    if columnar:
        return json.dumps({"positions": np.asarray(chunk.positions).tolist(), "source": chunk.source_id,
                           "seq": chunk.seq, "channels": {k: np.asarray(v).tolist() for k, v in chunk.channels.items()}})
    pts = []
    cols = {k: np.asarray(v).tolist() for k, v in chunk.channels.items()}
    for i, (x, y, z) in enumerate(np.asarray(chunk.positions).tolist()):
        pts.append({"x": x, "y": y, "z": z, "attributes": {k: v[i] for k, v in cols.items()}})
    return json.dumps({"points": pts, "source": chunk.source_id, "seq": chunk.seq})
