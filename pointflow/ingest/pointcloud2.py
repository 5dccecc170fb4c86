"""``sensor_msgs/PointCloud2`` -> :class:`PointChunk`: the one decoder every ROS path uses.

A PointCloud2 is rows of fixed-size points described by ``fields`` (name, byte offset,
datatype 1-8 = INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64, count). The
decoder builds one numpy structured dtype with the fields' explicit offsets and
``itemsize = point_step`` (so trailing padding and unsorted fields cost nothing), byte order
from ``is_bigendian``, and views ``data`` as a ``(height, width)`` array with strides
``(row_step, point_step)`` (rows may be padded); each wanted field is then copied out once,
in native byte order. No Python runs per point.

* ``x``, ``y``, ``z`` -> positions (float32 when they are float32, else float64). NaN points
  of organised clouds (``height > 1``, ``is_dense: false``) are passed through: ingest drops
  them and counts them as ``non_finite`` like every other non-finite point.
* packed ``rgb`` / ``rgba`` (float32 or uint32 holding 0x00RRGGBB, PCL style) -> ``rgb``
  (N, 3) uint8; separate ``r``/``g``/``b`` (or ``red``/``green``/``blue``) fields too.
* ``header.frame_id`` -> ``PointChunk.frame_id`` (leading ``/`` dropped), for the frames step.
* any other field -> a channel of the same name and dtype ((N, count) when ``count > 1``),
  then ``rename`` and the ``channels`` filter of the transport apply (e.g. Ouster
  ``reflectivity`` -> ``intensity``). Fields the filter drops are never copied.

A message that cannot be decoded raises :class:`ChunkError` whose reason is counted by the
transport: ``truncated`` (``data`` shorter than the cloud needs), ``field_overflow`` (a
field ends past ``point_step``), ``unknown_datatype``, ``no_xyz``, ``bad_field`` (duplicate
name, bad count), ``bad_layout`` (``row_step < width * point_step``, negative sizes),
``bad_shape`` (a message without the PointCloud2 keys). The message text names the field.

Messages come as rosbags objects (attributes) or rosbridge dicts (keys); :func:`decode`
takes either.
"""
from __future__ import annotations

import base64
import binascii
from typing import Any, Mapping, Optional, Sequence

import numpy as np

from ..chunk import ChunkError, PointChunk

#: PointField datatype -> numpy type code (without byte order).
DATATYPES: dict[int, str] = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
DATATYPE_NAMES: dict[int, str] = {1: "INT8", 2: "UINT8", 3: "INT16", 4: "UINT16", 5: "INT32", 6: "UINT32",
                                  7: "FLOAT32", 8: "FLOAT64"}
#: Type names a PointCloud2 goes by (ROS 2 and ROS 1 spelling).
MSGTYPES = ("sensor_msgs/msg/PointCloud2", "sensor_msgs/PointCloud2")
_PACKED_RGB = ("rgb", "rgba")
_RGB_TRIOS = (("r", "g", "b"), ("red", "green", "blue"))


def _get(obj: Any, key: str) -> Any:
    """A message field from a rosbags object or a rosbridge dict."""
    if isinstance(obj, Mapping):
        if key not in obj:
            raise ChunkError("bad_shape", f"PointCloud2 message has no {key!r}")
        return obj[key]
    try:
        return getattr(obj, key)
    except AttributeError:
        raise ChunkError("bad_shape", f"PointCloud2 message has no {key!r}") from None


def _int(obj: Any, key: str, what: str = "") -> int:
    v = _get(obj, key)
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
        raise ChunkError("bad_shape", f"{what or key} must be an integer, got {type(v).__name__}")
    return int(v)


def _as_bytes(data: Any) -> memoryview:
    """``data`` as bytes: a numpy uint8 array (rosbags), bytes (CBOR), base64 text (rosbridge
    JSON), a list of ints (old rosbridge) or a CBOR typed-array tag."""
    if isinstance(data, np.ndarray):
        return memoryview(np.ascontiguousarray(data).view(np.uint8).reshape(-1))
    if isinstance(data, (bytes, bytearray, memoryview)):
        return memoryview(data).cast("B")
    if isinstance(data, str):
        try:
            return memoryview(base64.b64decode(data, validate=True))
        except (binascii.Error, ValueError):
            raise ChunkError("bad_data", "field 'data' is a string but not valid base64") from None
    if isinstance(data, list):
        try:
            return memoryview(np.asarray(data, dtype=np.uint8).reshape(-1))
        except (TypeError, ValueError, OverflowError):
            raise ChunkError("bad_data", "field 'data' must hold bytes 0..255") from None
    tag_value = getattr(data, "value", None)  # cbor2.CBORTag (typed array): its payload is the bytes
    if isinstance(tag_value, (bytes, bytearray)):
        return memoryview(tag_value)
    raise ChunkError("bad_data", f"field 'data' must be bytes, got {type(data).__name__}")


def frame_id(msg: Any) -> str:
    """``header.frame_id`` without a leading ``/`` (ROS 1 style), "" when absent."""
    try:
        f = _get(_get(msg, "header"), "frame_id")
    except ChunkError:
        return ""
    return f.lstrip("/") if isinstance(f, str) else ""


def stamp_ns(msg: Any) -> int:
    """``header.stamp`` in ns (ROS 2 sec/nanosec or ROS 1 secs/nsecs); 0 when absent."""
    try:
        st = _get(_get(msg, "header"), "stamp")
    except ChunkError:
        return 0
    for s, ns in (("sec", "nanosec"), ("secs", "nsecs")):
        try:
            sec, nsec = _get(st, s), _get(st, ns)
        except ChunkError:
            continue
        if isinstance(sec, (int, np.integer)) and isinstance(nsec, (int, np.integer)):
            return int(sec) * 1_000_000_000 + int(nsec)
    return 0


class FieldPlan:
    """The parsed layout of one cloud: the structured dtype and what to copy out.

    Built once per distinct (fields, point_step, endianness, rename, keep); a stream of
    same-layout messages reuses it (see :class:`PointCloud2Decoder`)."""

    def __init__(self, fields: Sequence[tuple[str, int, int, int]], point_step: int, big: bool,
                 rename: Mapping[str, str], keep: Optional[Sequence[str]], always: Sequence[str] = ()):
        end = ">" if big else "<"
        names, formats, offsets = [], [], []
        seen: set[str] = set()
        by_name: dict[str, tuple[int, int, int]] = {}
        for name, offset, datatype, count in fields:
            if datatype not in DATATYPES:
                raise ChunkError("unknown_datatype", f"field {name!r} has unknown datatype {datatype} "
                                 f"(expected 1..8: {', '.join(DATATYPE_NAMES.values())})")
            if count < 0:
                raise ChunkError("bad_field", f"field {name!r} has count {count}")
            if not name or name in seen:
                raise ChunkError("bad_field", f"field {name!r} is {'listed twice' if name else 'unnamed'}")
            seen.add(name)
            if count == 0:  # takes no bytes: nothing to read
                continue
            size = int(DATATYPES[datatype][1]) * count
            if offset < 0 or offset + size > point_step:
                raise ChunkError("field_overflow", f"field {name!r} ({DATATYPE_NAMES[datatype]} x{count} at offset "
                                 f"{offset}) ends at byte {offset + size}, beyond point_step {point_step}")
            by_name[name] = (offset, datatype, count)
        for k in ("x", "y", "z"):
            if k not in by_name:
                raise ChunkError("no_xyz", f"no field {k!r} (fields: {', '.join(f[0] for f in fields) or 'none'})")
            if by_name[k][2] != 1:
                raise ChunkError("no_xyz", f"field {k!r} has count {by_name[k][2]}; x, y, z must be one value each")
        for name, (offset, datatype, count) in by_name.items():
            code = DATATYPES[datatype]
            if name in _PACKED_RGB and count == 1 and datatype in (6, 7):
                code = "u4"  # packed colour: reinterpret the float32 bits
            names.append(name)
            formats.append(np.dtype(end + code) if count == 1 else np.dtype((end + code, (count,))))
            offsets.append(offset)
        self.dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})
        x, y, z = (by_name[k] for k in ("x", "y", "z"))
        self.pos_kind = "f4" if x[1] == y[1] == z[1] == 7 else "f8"
        # x, y, z adjacent and of one type (the usual layout): one (3,) sub-array copy
        self.xyz_block: Optional[np.dtype] = None
        sz = int(DATATYPES[x[1]][1])
        if x[1] == y[1] == z[1] and y[0] == x[0] + sz and z[0] == x[0] + 2 * sz:
            self.xyz_block = np.dtype({"names": ["xyz"], "formats": [np.dtype((end + DATATYPES[x[1]], (3,)))],
                                       "offsets": [x[0]], "itemsize": point_step})
        # channels: (field, output name) for what survives rename + keep
        self.channels: list[tuple[str, str]] = []
        self.rgb: Optional[tuple[str, ...]] = None
        want = None if keep is None else set(keep)
        used = {"x", "y", "z"}
        if rename.get("rgb", "rgb") in (want if want is not None else {"rgb"}):
            for p in _PACKED_RGB:
                if p in by_name and by_name[p][2] == 1 and by_name[p][1] in (6, 7):
                    self.rgb = (p,)
                    used.add(p)
                    break
            else:
                for trio in _RGB_TRIOS:
                    if all(t in by_name and by_name[t][2] == 1 for t in trio):
                        self.rgb = trio
                        used.update(trio)
                        break
        else:
            used.update(p for p in _PACKED_RGB if p in by_name and by_name[p][1] in (6, 7))
        self.rgb_name = rename.get("rgb", "rgb")
        for name in by_name:
            if name in used:
                continue
            out = rename.get(name, name)
            if want is None or out in want:
                self.channels.append((name, out))
            elif name in always:  # per-point times for deskew (docs/frames.md): kept under their own name
                self.channels.append((name, name))


def _native(a: np.ndarray) -> np.ndarray:
    """A contiguous native-endian copy of a (strided) field view."""
    dt = a.dtype
    if dt.byteorder == ">" or (dt.byteorder == "<" and not np.little_endian):
        dt = dt.newbyteorder("=")
    return np.array(a, dtype=dt, order="C")


class PointCloud2Decoder:
    """Decodes PointCloud2 messages of one stream (the layout plan is cached)."""

    def __init__(self, rename: Optional[Mapping[str, str]] = None, channels: Optional[Sequence[str]] = None,
                 always: Sequence[str] = ()):
        self.rename = dict(rename or {})
        self.keep = list(channels) if channels is not None else None
        #: Fields kept whatever ``channels`` says (the per-point time fields when deskew is on).
        self.always = tuple(always)
        self._plan_key: Any = None
        self._plan: Optional[FieldPlan] = None

    def _plan_for(self, fields_raw: Any, point_step: int, big: bool) -> FieldPlan:
        if not isinstance(fields_raw, (list, tuple)):
            raise ChunkError("bad_shape", f"'fields' must be a list, got {type(fields_raw).__name__}")
        fields = []
        for i, f in enumerate(fields_raw):
            name = _get(f, "name")
            if not isinstance(name, str):
                raise ChunkError("bad_field", f"fields[{i}].name must be a string")
            fields.append((name, _int(f, "offset", f"field {name!r} offset"), _int(f, "datatype", f"field {name!r} datatype"),
                           _int(f, "count", f"field {name!r} count")))
        key = (tuple(fields), point_step, big)
        if key != self._plan_key:
            self._plan = FieldPlan(fields, point_step, big, self.rename, self.keep, self.always)
            self._plan_key = key
        assert self._plan is not None
        return self._plan

    def decode(self, msg: Any, source_id: str = "") -> PointChunk:
        """One message -> chunk (``stamp_ns`` from its header); raises :class:`ChunkError`."""
        width = _int(msg, "width")
        height = _int(msg, "height")
        point_step = _int(msg, "point_step")
        row_step = _int(msg, "row_step")
        big = bool(_get(msg, "is_bigendian"))
        if width < 0 or height < 0 or point_step < 0:
            raise ChunkError("bad_layout", f"negative size: width {width}, height {height}, point_step {point_step}")
        plan = self._plan_for(_get(msg, "fields"), point_step, big)
        n = width * height
        if height > 1 and row_step < width * point_step:
            raise ChunkError("bad_layout", f"row_step {row_step} is smaller than width {width} x point_step {point_step}")
        if height <= 1 or row_step < width * point_step:
            row_step = width * point_step  # one row: row_step does not matter
        buf = _as_bytes(_get(msg, "data"))
        need = (height - 1) * row_step + width * point_step if n else 0
        if buf.nbytes < need:
            raise ChunkError("truncated", f"field 'data' has {buf.nbytes} bytes; {height} x {width} points at "
                             f"point_step {point_step}, row_step {row_step} need {need}")
        stamp = stamp_ns(msg)
        frame = frame_id(msg)
        if n == 0:
            pos = np.zeros((0, 3), np.float32 if plan.pos_kind == "f4" else np.float64)
            chans = {c: np.zeros((0,) + plan.dtype[f].shape, plan.dtype[f].base.newbyteorder("="))
                     for f, c in plan.channels}
            if plan.rgb:
                chans[plan.rgb_name] = np.zeros((0, 3), np.uint8)
            return PointChunk(positions=pos, channels=chans, source_id=source_id, stamp_ns=stamp, frame_id=frame)

        def view(dt: np.dtype) -> np.ndarray:
            return np.ndarray((height, width), dtype=dt, buffer=buf, offset=0, strides=(row_step, point_step))

        rec = view(plan.dtype)
        if plan.xyz_block is not None:
            xyz = view(plan.xyz_block)["xyz"]
            pos = np.array(xyz, dtype=plan.pos_kind, order="C").reshape(n, 3)
        else:
            pos = np.empty((n, 3), plan.pos_kind)
            for j, k in enumerate("xyz"):
                pos[:, j] = rec[k].reshape(n)
        chans: dict[str, np.ndarray] = {}
        for f, out in plan.channels:
            a = _native(rec[f])
            chans[out] = a.reshape((n,) + a.shape[2:])
        if plan.rgb is not None:
            if len(plan.rgb) == 1:
                u = np.array(rec[plan.rgb[0]], dtype="<u4", order="C").reshape(n)
                rgb = u.view(np.uint8).reshape(n, 4)[:, 2::-1]  # little-endian bytes b, g, r, a -> r, g, b
                chans[plan.rgb_name] = np.ascontiguousarray(rgb)
            else:
                cols = [rec[t].reshape(n) for t in plan.rgb]
                kind = np.uint8 if all(c.dtype.itemsize == 1 for c in cols) else np.uint16
                if any(c.dtype.kind == "f" for c in cols):
                    arr = np.column_stack(cols).astype(np.float32)
                    scale = 255.0 if arr.size and float(np.nanmax(arr)) <= 1.0 else 1.0
                    chans[plan.rgb_name] = np.clip(np.rint(np.nan_to_num(arr) * scale), 0, 255).astype(np.uint8)
                else:
                    chans[plan.rgb_name] = np.column_stack(cols).astype(kind)
        return PointChunk(positions=pos, channels=chans, source_id=source_id, stamp_ns=stamp, frame_id=frame)


def decode(msg: Any, rename: Optional[Mapping[str, str]] = None, channels: Optional[Sequence[str]] = None,
           source_id: str = "") -> PointChunk:
    """Decode one PointCloud2 (a rosbags message or a rosbridge dict); see the module doc."""
    return PointCloud2Decoder(rename, channels).decode(msg, source_id)
