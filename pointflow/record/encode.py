"""Point chunks -> ROS 2 ``sensor_msgs/msg/PointCloud2`` messages in CDR.

The cloud is one row (``height`` 1) of packed points: x, y, z (FLOAT32, or FLOAT64 when
ingest holds float64 positions), then each recorded channel at the next byte, with no
padding. ``rgb`` (N, 3) uint8 is packed into one FLOAT32 field holding 0x00RRGGBB, the
PCL convention Foxglove, Rerun and RViz colour by; any other (N, k) channel is one field
with ``count = k``. The points are packed with numpy column copies into one buffer and the
few header fields around it are written with ``struct``: no Python runs per point.

CDR (XCDR1, little endian) is the ROS 2 wire format: a 4-byte encapsulation header, then
the fields in order, each aligned to its size relative to the end of that header.
"""
from __future__ import annotations

import struct
from typing import Sequence

import numpy as np

#: The message definition stored in the file's schema record (ros2msg encoding, the form
#: ``ros2 bag`` and Foxglove write: the type, then each dependency after a ``=`` line).
#: The std_msgs/Header dependency (and its Time) both schemas below carry.
_HEADER_DEFS = """\
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
"""
SCHEMA_NAME = "sensor_msgs/msg/PointCloud2"
SCHEMA_TEXT = """\
std_msgs/Header header
uint32 height
uint32 width
PointField[] fields
bool is_bigendian
uint32 point_step
uint32 row_step
uint8[] data
bool is_dense
""" + _HEADER_DEFS + """\
================================================================================
MSG: sensor_msgs/PointField
uint8 INT8    = 1
uint8 UINT8   = 2
uint8 INT16   = 3
uint8 UINT16  = 4
uint8 INT32   = 5
uint8 UINT32  = 6
uint8 FLOAT32 = 7
uint8 FLOAT64 = 8
string name
uint32 offset
uint8  datatype
uint32 count
"""

#: numpy dtype -> PointField datatype. 64-bit integers have none: they are stored as FLOAT64.
DATATYPE = {np.dtype("int8"): 1, np.dtype("uint8"): 2, np.dtype("int16"): 3, np.dtype("uint16"): 4,
            np.dtype("int32"): 5, np.dtype("uint32"): 6, np.dtype("float32"): 7, np.dtype("float64"): 8}
_CDR_LE = b"\x00\x01\x00\x00"


def _pad(n: int, align: int) -> int:
    return (-n) % align


class _Cdr:
    """Append-only CDR writer for the message's few header fields."""

    def __init__(self) -> None:
        self.parts: list[bytes] = [_CDR_LE]
        self.n = 0  # bytes after the encapsulation header (alignment origin)

    def raw(self, b: bytes) -> None:
        self.parts.append(b)
        self.n += len(b)

    def align(self, a: int) -> None:
        p = _pad(self.n, a)
        if p:
            self.raw(b"\x00" * p)

    def u32(self, v: int) -> None:
        self.align(4)
        self.raw(struct.pack("<I", v))

    def i32(self, v: int) -> None:
        self.align(4)
        self.raw(struct.pack("<i", v))

    def u8(self, v: int) -> None:
        self.raw(bytes((v,)))

    def string(self, s: str) -> None:
        b = s.encode() + b"\x00"
        self.u32(len(b))
        self.raw(b)


class Layout:
    """The packed field layout of one (positions dtype, channel set); built once per
    distinct layout and reused for every message of a stream."""

    def __init__(self, pos_dtype: np.dtype, channels: Sequence[tuple[str, np.dtype, int]]):
        pos_dtype = np.dtype(pos_dtype)
        self.fields: list[tuple[str, int, int, int]] = []  # name, offset, datatype, count
        self.copy: list[tuple[str, int, np.dtype, int]] = []  # channel, offset, stored dtype, count
        psize = pos_dtype.itemsize
        for i, k in enumerate("xyz"):
            self.fields.append((k, i * psize, DATATYPE[pos_dtype], 1))
        self.pos_dtype = pos_dtype
        off = 3 * psize
        for name, dt, width in channels:
            dt = np.dtype(dt)
            if name == "rgb" and dt == np.uint8 and width == 3:
                self.fields.append(("rgb", off, 7, 1))  # packed 0x00RRGGBB in a FLOAT32 (PCL)
                self.copy.append((name, off, np.dtype("<u4"), 0))
                off += 4
                continue
            store = dt if dt in DATATYPE else np.dtype("float64")
            self.fields.append((name, off, DATATYPE[store], width))
            self.copy.append((name, off, store.newbyteorder("<"), width))
            off += store.itemsize * width
        self.point_step = off
        # the fields part of the message is the same for every message of this layout
        self._fields_cdr_cache: dict[int, bytes] = {}

    def fields_cdr(self, start: int) -> bytes:
        """The ``fields`` sequence encoded at byte ``start`` (its alignment depends on it)."""
        key = start % 8
        b = self._fields_cdr_cache.get(key)
        if b is None:
            w = _Cdr()
            w.parts = []
            w.n = start
            w.u32(len(self.fields))
            for name, offset, datatype, count in self.fields:
                w.string(name)
                w.u32(offset)
                w.u8(datatype)
                w.u32(count)
            b = self._fields_cdr_cache[key] = b"".join(w.parts)
        return b

    def pack(self, buf: np.ndarray, positions: np.ndarray, channels: dict[str, np.ndarray]) -> None:
        """Write the packed points (little endian) into ``buf``, an (N, point_step) uint8 view."""
        n = positions.shape[0]
        psize = self.pos_dtype.itemsize
        buf[:, :3 * psize].view(self.pos_dtype.newbyteorder("<"))[...] = positions
        for name, off, dt, width in self.copy:
            a = channels[name]
            if width == 0:  # rgb (N, 3) uint8 -> 0x00RRGGBB
                a = a.astype(np.uint32)
                buf[:, off:off + 4].view(dt)[:, 0] = (a[:, 0] << 16) | (a[:, 1] << 8) | a[:, 2]
            elif width == 1:
                buf[:, off:off + dt.itemsize].view(dt)[:, 0] = a.reshape(n)
            else:
                buf[:, off:off + dt.itemsize * width].view(dt)[...] = a.reshape(n, width)


class Scratch:
    """A reusable output buffer: a fresh 1 MB array per message costs page faults (the kernel
    zeroing new pages) that, next to file writes, took longer than the packing itself. The
    ``mcap`` writer copies a message into its chunk before ``add_message`` returns, so the
    buffer can be reused for the next one."""

    def __init__(self) -> None:
        self.buf = np.empty(0, np.uint8)

    def get(self, n: int) -> np.ndarray:
        if self.buf.size < n:
            self.buf = np.empty(max(n, int(self.buf.size * 1.25)), np.uint8)
        return self.buf[:n]


def encode_pointcloud2(layout: Layout, positions: np.ndarray, channels: dict[str, np.ndarray],
                       stamp_ns: int, frame_id: str, scratch: Scratch | None = None) -> memoryview:
    """The CDR bytes of one message: the header fields, then the points packed straight
    into the same buffer (one copy of the point data). With ``scratch`` the bytes live in its
    buffer and are valid until the next call."""
    n = positions.shape[0]
    nbytes = layout.point_step * n
    w = _Cdr()
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    w.i32(sec)
    w.u32(nsec)
    w.string(frame_id)
    w.u32(1)  # height
    w.u32(n)  # width
    w.raw(layout.fields_cdr(w.n))
    w.u8(0)   # is_bigendian
    w.u32(layout.point_step)
    w.u32(nbytes)  # row_step
    w.u32(nbytes)  # data: uint8[] length, then the bytes (no alignment)
    head = b"".join(w.parts)
    size = len(head) + nbytes + 1
    out = scratch.get(size) if scratch is not None else np.empty(size, np.uint8)
    out[:len(head)] = np.frombuffer(head, np.uint8)
    if n:
        layout.pack(out[len(head):len(head) + nbytes].reshape(n, layout.point_step), positions, channels)
    out[-1] = 1  # is_dense: ingest passes only finite points
    return memoryview(out)


def layout_key(positions: np.ndarray, channels: dict[str, np.ndarray]) -> tuple:
    return (positions.dtype.str,) + tuple((k, v.dtype.str, 1 if v.ndim == 1 else v.shape[1])
                                          for k, v in channels.items())


#: ``/tf`` and ``/tf_static`` (docs/record.md): the transforms ingest received, as the ROS 2
#: ``tf2_msgs/msg/TFMessage`` so Foxglove, Rerun and RViz show the frame tree. The text is the
#: ROS 2 ``.msg`` files with their dependencies, as ``ros2 bag`` stores it.
TF_SCHEMA_NAME = "tf2_msgs/msg/TFMessage"
TF_SCHEMA_TEXT = """\
geometry_msgs/TransformStamped[] transforms
================================================================================
MSG: geometry_msgs/TransformStamped
std_msgs/Header header
string child_frame_id
Transform transform
""" + _HEADER_DEFS + """\
================================================================================
MSG: geometry_msgs/Transform
Vector3 translation
Quaternion rotation
================================================================================
MSG: geometry_msgs/Vector3
float64 x
float64 y
float64 z
================================================================================
MSG: geometry_msgs/Quaternion
float64 x 0
float64 y 0
float64 z 0
float64 w 1
"""
_tf_encoder = None


def encode_tf(transforms) -> bytes:
    """The CDR bytes of one ``TFMessage`` holding ``transforms``
    (:class:`pointflow.frames.message.Transform`), encoded by ``mcap-ros2-support`` from the
    schema text above (a few messages a second: no need for a hand-written encoder)."""
    global _tf_encoder
    if _tf_encoder is None:
        from mcap_ros2._dynamic import serialize_dynamic

        _tf_encoder = serialize_dynamic(TF_SCHEMA_NAME, TF_SCHEMA_TEXT)[TF_SCHEMA_NAME]
    items = []
    for t in transforms:
        sec, nsec = divmod(int(t.stamp_ns), 1_000_000_000)
        tx, ty, tz = (float(v) for v in t.translation)
        rx, ry, rz, rw = (float(v) for v in t.rotation)
        items.append({"header": {"stamp": {"sec": sec, "nanosec": nsec}, "frame_id": t.parent},
                      "child_frame_id": t.child,
                      "transform": {"translation": {"x": tx, "y": ty, "z": tz},
                                    "rotation": {"x": rx, "y": ry, "z": rz, "w": rw}}})
    return _tf_encoder({"transforms": items})
