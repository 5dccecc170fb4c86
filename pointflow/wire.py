"""The ZeroMQ wire format for point chunks (documented in docs/wire-format.md).

A chunk is one multipart message::

    frame 0   header: UTF-8 JSON object (schema, counts, dtypes, shapes, sequence, times)
    frame 1   positions: N*3 values, row-major, dtype from the header
    frame 2+  one raw frame per channel, in the order the header lists them

or, packed (``"packed": true`` in the header; what :func:`encode` writes for chunks under
:data:`PACK_MAX_BYTES`), the header and one frame holding every array, each at a multiple of
:data:`PACK_ALIGN` bytes (docs/wire-format.md "Packed chunks"). Data frames are byte views on
the arrays, sent with ``copy=False``: pyzmq copies one below its copy threshold
(:data:`ZERO_COPY_MIN_BYTES`) once and sends a larger one without a copy. Any language that
can write JSON and bytes can send.
"""
from __future__ import annotations

import json
import re
import struct
import time
from typing import Any, Sequence

import numpy as np
from zmq import Frame as _Frame

from .chunk import SUPPORTED_DTYPES, ChunkError, PointChunk

SCHEMA = "pointflow.chunk/1"
#: pyzmq's zero-copy send pays off above roughly this size.
ZERO_COPY_MIN_BYTES = 64 * 1024
#: A header larger than this is rejected before JSON parsing.
MAX_HEADER_BYTES = 64 * 1024

_DTYPE_BY_NAME = {name: np.dtype(name).newbyteorder("<") for name in SUPPORTED_DTYPES}


_DTYPE_NAMES: dict[np.dtype, str] = {}


def _dtype_str(dt: np.dtype) -> str:
    # dtype.name is rebuilt on every access (~2 us); the names of the supported dtypes are cached
    name = _DTYPE_NAMES.get(dt)
    if name is None:
        name = dt.name
        if name in SUPPORTED_DTYPES:
            _DTYPE_NAMES[dt] = name
    return name


def encode(chunk: PointChunk, *, link: dict | None = None, compressor: Any = None,
           resolution: float | None = None, pack: bool = True) -> list[Any]:
    """Frames for ``socket.send_multipart(frames, copy=False)``; arrays are not copied
    unless they are not C-contiguous little-endian.

    A chunk whose data add up to less than :data:`PACK_MAX_BYTES` goes as two frames, its
    arrays packed into one (docs/wire-format.md "Packed chunks"), unless ``pack`` is False.
    A link may add a ``link`` header object (per-source link sequence, see
    :mod:`pointflow.remote.transit`), compress the data frames (a
    :class:`pointflow.codec.Compressor`) and quantise positions to ``resolution``;
    without those the output is the plain format, byte for byte."""
    if link is not None or compressor is not None or resolution:
        return _encode_link(chunk, link, compressor, resolution)
    pos = chunk.positions
    chans = chunk.channels
    try:
        key = (chunk.source_id, chunk.frame_id, not chunk.stamp_ns, pack, pos.dtype, pos.shape,
               *[(k, a.dtype, a.shape) for k, a in chans.items()])
        plan = _ENC_PLANS.get(key, _ENC_PLANS)
    except (AttributeError, TypeError):  # not arrays, unhashable names: the general path reports it
        plan = None
    if plan is _ENC_PLANS:
        plan = _enc_plan(chunk, pack)
        if len(_ENC_PLANS) >= _PLANS_MAX:
            _ENC_PLANS.clear()
        _ENC_PLANS[key] = plan
    if plan is not None and pos.flags.c_contiguous and all(a.flags.c_contiguous for a in chans.values()):
        tpl, pads = plan
        t_sent = chunk.t_sent_ns or time.monotonic_ns()
        head = tpl % ((chunk.seq, chunk.trace_id, t_sent, chunk.stamp_ns) if chunk.stamp_ns
                      else (chunk.seq, chunk.trace_id, t_sent))
        return _frames(head, (pos, *chans.values()), pads)
    return _encode_general(chunk, pack)


#: Chunks whose data frames add up to less than this go packed into one data frame
#: (docs/wire-format.md "Packed chunks"): below pyzmq's zero-copy size every frame is copied
#: anyway, and each frame saved is work saved on both ends and both ZeroMQ I/O threads.
PACK_MAX_BYTES = ZERO_COPY_MIN_BYTES
#: In a packed frame every array starts at a multiple of this many bytes.
PACK_ALIGN = 8
_ZEROS = bytes(PACK_ALIGN)
#: (source, frame, stamp absent, pack, dtypes, shapes) -> (header template, pads) for
#: :func:`encode`: the header text of a stream's chunks differs only in seq, trace and times.
_ENC_PLANS: dict[tuple, Any] = {}


class _Slot:
    """Stands for a per-chunk number while a header template is written."""

    def __repr__(self) -> str:
        return "\x00"  # never in a JSON text (escaped there as \\u0000)


_SLOT = _Slot()


def _packed_offsets(nbytes: Sequence[int]) -> tuple[list[int], int]:
    """Where each array starts in a packed frame (each at a multiple of PACK_ALIGN, in header
    order, positions first) and the frame's size (no padding after the last)."""
    offsets, end = [], 0
    for nb in nbytes:
        off = end + (-end % PACK_ALIGN)
        offsets.append(off)
        end = off + nb
    return offsets, end


def _pack_pads(nbytes: Sequence[int], pack: bool) -> list[int] | None:
    """Zero bytes before each array after the first in a packed frame, or None when the
    arrays go as a frame each (``pack`` False, a single array, or PACK_MAX_BYTES reached)."""
    if not pack or len(nbytes) < 2 or sum(nbytes) + PACK_ALIGN * len(nbytes) >= PACK_MAX_BYTES:
        return None
    offsets, _ = _packed_offsets(nbytes)
    return [offsets[i + 1] - offsets[i] - nbytes[i] for i in range(len(nbytes) - 1)]


def _frames(head: bytes, arrays: Sequence[np.ndarray], pads: list[int] | None) -> list[Any]:
    """The header and the data frames of contiguous little-endian arrays: one packed frame
    (``pads`` from :func:`_pack_pads`), or a byte view each, which pyzmq copies once below its
    copy threshold and sends without a copy above it."""
    if pads is None:
        return [head, *[memoryview(a).cast("B") if a.nbytes else b"" for a in arrays]]
    parts: list[Any] = [arrays[0]]
    for pad, a in zip(pads, arrays[1:]):
        if pad:
            parts.append(_ZEROS[:pad])
        parts.append(a)
    return [head, b"".join(parts)]


def _enc_plan(chunk: PointChunk, pack: bool) -> Any:
    """(header template with %d for seq, trace, t_sent_ns and stamp_ns; the pads of a packed
    frame, or None when the data go as a frame each), or None when this chunk's arrays need
    the general path (not arrays, big-endian, an unsupported dtype, non-str names)."""
    arrays = [chunk.positions, *chunk.channels.values()]
    names = [chunk.source_id, chunk.frame_id, *chunk.channels]
    if (not all(type(a) is np.ndarray and a.dtype.byteorder != ">" and a.dtype.name in SUPPORTED_DTYPES for a in arrays)
            or not all(type(s) is str for s in names) or arrays[0].ndim != 2 or arrays[0].shape[1] != 3):
        return None
    pads = _pack_pads([a.nbytes for a in arrays], pack)
    h = _header(chunk, arrays[0], list(chunk.channels.items()), _SLOT, _SLOT,
                _SLOT, _SLOT if chunk.stamp_ns else 0, pads is not None)
    return _header_json(h).replace(b"%", b"%%").replace(b"\x00", b"%d"), pads


def _header(chunk: PointChunk, pos: np.ndarray, chans: Sequence[tuple[str, np.ndarray]], seq: Any, trace: Any,
            t_sent: Any, stamp: Any, packed: bool) -> dict:
    n = int(pos.shape[0])
    header = {
        "schema": SCHEMA, "source": chunk.source_id, "seq": seq, "trace": trace, "t_sent_ns": t_sent, "n": n,
        "positions": {"dtype": _dtype_str(pos.dtype), "shape": [n, 3]},
        "channels": [{"name": k, "dtype": _dtype_str(a.dtype), "shape": list(a.shape)} for k, a in chans],
    }
    if packed:
        header["packed"] = True
    if stamp:  # optional: only sources with a capture time (ROS header.stamp) send it
        header["stamp_ns"] = stamp
    if chunk.frame_id:  # optional: the coordinate frame (docs/frames.md)
        header["frame"] = chunk.frame_id
    return header


def _encode_general(chunk: PointChunk, pack: bool) -> list[Any]:
    """:func:`encode` for any chunk (copies what is not contiguous little-endian)."""
    arrays = []
    for a in (chunk.positions, *chunk.channels.values()):
        a = np.ascontiguousarray(a)
        if a.dtype.byteorder == ">":
            a = a.astype(a.dtype.newbyteorder("<"))
        arrays.append(a)
    pads = _pack_pads([a.nbytes for a in arrays], pack)
    h = _header(chunk, arrays[0], list(zip(chunk.channels, arrays[1:])), int(chunk.seq), int(chunk.trace_id),
                int(chunk.t_sent_ns or time.monotonic_ns()), int(chunk.stamp_ns), pads is not None)
    return _frames(_header_json(h), arrays, pads)


_json_str = json.encoder.encode_basestring_ascii  # what json.dumps uses for str (ensure_ascii)


def _header_json(h: dict) -> bytes:
    """``json.dumps(h, separators=(",", ":")).encode()``, byte for byte, in a third of the time
    for the usual header (str source and channel names, int counts); anything else goes
    through json.dumps."""
    src = h["source"]
    chans = h["channels"]
    if type(src) is not str or not all(type(c["name"]) is str for c in chans) or type(h.get("frame", "")) is not str:
        return json.dumps(h, separators=(",", ":")).encode()
    parts = [f'{{"schema":{_json_str(h["schema"])},"source":{_json_str(src)},"seq":{h["seq"]!r},'
             f'"trace":{h["trace"]!r},"t_sent_ns":{h["t_sent_ns"]!r},"n":{h["n"]!r},'
             f'"positions":{{"dtype":{_json_str(h["positions"]["dtype"])},"shape":[{h["n"]!r},3]}},"channels":[']
    for i, c in enumerate(chans):
        shape = ",".join([repr(int(x)) for x in c["shape"]])
        parts.append(f'{"," if i else ""}{{"name":{_json_str(c["name"])},"dtype":{_json_str(c["dtype"])},"shape":[{shape}]}}')
    parts.append('],"packed":true' if h.get("packed") is True else "]")
    if "stamp_ns" in h:
        parts.append(f',"stamp_ns":{h["stamp_ns"]!r}')
    parts.append(f',"frame":{_json_str(h["frame"])}}}' if "frame" in h else "}")
    return "".join(parts).encode()


def _encode_link(chunk: PointChunk, link: dict | None, compressor: Any, resolution: float | None) -> list[Any]:
    """The encoded form (docs/wire-format.md, "Encoded chunks")."""
    from . import codec

    pos = np.ascontiguousarray(chunk.positions)
    n = int(pos.shape[0])
    pos_meta: dict[str, Any] = {"dtype": _dtype_str(pos.dtype), "shape": [n, 3]}
    if resolution:
        qo = codec.quantise(pos, resolution)
        if qo is not None:  # else (too wide for int32, non-finite) the floats go as they are
            pos = qo[0]
            pos_meta = {"dtype": "int32", "shape": [n, 3], "origin": qo[1], "resolution": float(resolution)}
    arrays = [pos]
    chans = []
    for name, arr in chunk.channels.items():
        a = np.ascontiguousarray(arr)
        chans.append({"name": name, "dtype": _dtype_str(a.dtype), "shape": list(a.shape)})
        arrays.append(a)
    header: dict[str, Any] = {
        "schema": SCHEMA, "source": chunk.source_id, "seq": int(chunk.seq), "trace": int(chunk.trace_id),
        "t_sent_ns": int(chunk.t_sent_ns or time.monotonic_ns()), "n": n, "positions": pos_meta, "channels": chans,
    }
    if chunk.stamp_ns:
        header["stamp_ns"] = int(chunk.stamp_ns)
    if chunk.frame_id:
        header["frame"] = chunk.frame_id
    if link is not None:
        header["link"] = link
    frames: list[Any] = [json.dumps(header, separators=(",", ":")).encode()]
    if compressor is not None:
        header_codec = {"codec": compressor.codec, "shuffle": bool(compressor.shuffle)}
        header.update(header_codec)
        frames[0] = json.dumps(header, separators=(",", ":")).encode()
        frames += [compressor.frame(a.astype(a.dtype.newbyteorder("<"), copy=False)) for a in arrays]
    else:
        for a in arrays:
            if a.dtype.byteorder == ">":
                a = a.astype(a.dtype.newbyteorder("<"))
            frames.append(memoryview(a).cast("B") if a.nbytes >= ZERO_COPY_MIN_BYTES else a.tobytes())
    return frames


def to_single(frames: Sequence[Any]) -> tuple[bytes, bytes]:
    """One message of :func:`encode` as ``(header, body)`` for engines that carry one payload
    and an attachment per message (Zenoh links, docs/wire-format.md "Single-buffer framing"):
    the header frame as it is, and the data frames back to back after their count (u32) and
    byte lengths (u64 each), little-endian. The data frames are copied once, into the body."""
    data = frames[1:]
    lens = [f.nbytes if isinstance(f, memoryview) else len(f) for f in data]
    return bytes(frames[0]), b"".join([struct.pack(f"<I{len(lens)}Q", len(lens), *lens), *data])


def from_single(header: Any, body: Any) -> list[Any]:
    """The frames of a :func:`to_single` message (views on ``body``, no copy), for
    :func:`decode_message`; :class:`ChunkError` when the framing does not add up."""
    mv = memoryview(body).cast("B")
    if mv.nbytes < 4:
        raise ChunkError("bad_frame_count", f"single-buffer body of {mv.nbytes} bytes has no frame count")
    (k,) = struct.unpack_from("<I", mv, 0)
    start = 4 + 8 * k
    if k > 4096 or start > mv.nbytes:
        raise ChunkError("bad_frame_count", f"single-buffer body declares {k} frames in {mv.nbytes} bytes")
    lens = struct.unpack_from(f"<{k}Q", mv, 4)
    if start + sum(lens) != mv.nbytes:
        raise ChunkError("truncated" if start + sum(lens) > mv.nbytes else "size_mismatch",
                         f"single-buffer body: frames of {sum(lens)} bytes declared, {mv.nbytes - start} present")
    frames: list[Any] = [header]
    for n in lens:
        frames.append(mv[start:start + n])
        start += n
    return frames


def send(sock, chunk: PointChunk, flags: int = 0) -> None:
    """Send one chunk; large frames go without a copy."""
    sock.send_multipart(encode(chunk), flags=flags, copy=False)


def _buf(frame) -> memoryview:
    if isinstance(frame, (bytes, bytearray, memoryview)):
        return memoryview(frame)
    return frame.buffer  # zmq.Frame


_BIG_DIM = 2**40
_I64_WRAP, _I64_HALF = 1 << 64, 1 << 63


def _frame_spec(dtype_name: Any, shape: Sequence[int], what: str) -> tuple[np.dtype, tuple[int, ...], int]:
    """(dtype, shape, bytes) a data frame must have; ChunkError when the header's dtype or
    shape is not acceptable."""
    dt = _DTYPE_BY_NAME.get(dtype_name) if isinstance(dtype_name, str) else None
    if dt is None:
        raise ChunkError("bad_dtype", f"{what}: unsupported dtype {dtype_name!r}")
    if not isinstance(shape, (list, tuple)) or not 1 <= len(shape) <= 2:
        raise ChunkError("bad_header", f"{what}: bad shape {shape!r}")
    count = 1
    for s in shape:  # a plain loop: np.prod costs ~3 us per call, more than the rest of this function
        if not isinstance(s, int) or isinstance(s, bool) or not 0 <= s < _BIG_DIM:
            raise ChunkError("bad_header", f"{what}: bad shape {shape!r}")
        count *= s
    if count >= _I64_HALF:  # the product as int64 (wrapping), as np.prod(shape, dtype=int64) gave
        count = (count + _I64_HALF) % _I64_WRAP - _I64_HALF
    return dt, tuple(shape), count * dt.itemsize


def _array(frame, dtype_name: Any, shape: Sequence[int], what: str, codec: Any = None, shuffled: bool = False) -> np.ndarray:
    dt, _, expected = _frame_spec(dtype_name, shape, what)
    if codec is not None:
        from .codec import decompress

        buf = memoryview(decompress(_buf(frame), codec, expected, dt.itemsize, shuffled))
    else:
        buf = _buf(frame)
    if buf.nbytes != expected:
        raise ChunkError(
            "truncated" if buf.nbytes < expected else "size_mismatch",
            f"{what}: header promises {expected} bytes ({shape} x {dtype_name}), frame has {buf.nbytes}",
        )
    return np.frombuffer(buf, dtype=dt).reshape(shape)


def decode(frames: Sequence[Any], max_points: int | None = None) -> PointChunk:
    """Parse a multipart message; raises :class:`ChunkError` with a reason on any defect.

    The arrays returned are views on the received frames (no copy; read-only for bytes,
    writable for a ``zmq.Frame``, whose memory belongs to the receiver), except for
    compressed or quantised chunks, which are decoded into new arrays."""
    chunk = _decode_fast(frames, max_points)
    if chunk is not None:
        return chunk
    return decode_message(frames, max_points)[0]


_INT = rb"(-?(?:0|[1-9][0-9]*))"  # a JSON integer, as json.loads accepts it
_ID = rb'"([ !#-\[\]-~]*)"'  # a string the fast path takes as is: printable ASCII, no quote or backslash
#: A header as :func:`encode` writes it, whole: the fields that change with every chunk (seq,
#: trace, send time, capture stamp) around a part that stays the same for a stream (count,
#: dtypes, shapes, channel names, packing: the fifth group, parsed and checked once, see
#: :data:`_PLANS`), then the optional stamp and frame id. The fifth group runs to the last
#: "]" that leaves a valid ending (neither the stamp nor the frame id can hold a quote, so
#: there is one such split; what the group holds beyond the plain keys fails its check). A
#: header this does not match goes through decode_message.
_HEADER_RE = re.compile(
    rb'\{"schema":"pointflow\.chunk/1","source":' + _ID + rb',"seq":' + _INT + rb',"trace":' + _INT
    + rb',"t_sent_ns":' + _INT + rb',("n":.*\](?:,"packed":true)?)'
    + rb'(?:,"stamp_ns":' + _INT + rb')?(?:,"frame":' + _ID + rb')?\}', re.S)
#: The per-chunk-constant part of recent headers -> what decode_message would make of it
#: when the data frames have the promised sizes: (n, channel names, (dtype, shape, bytes or
#: offset) for positions and each channel, size of the packed frame or 0), or None when it
#: is anything but a plain chunk (slow path).
_PLANS: dict[bytes, Any] = {}
_PLANS_MAX = 256
_TAIL_MAX = 4096
_PLAIN_KEYS = frozenset(("n", "positions", "channels", "packed"))


def _decode_fast(frames: Sequence[Any], max_points: int | None) -> PointChunk | None:
    """:func:`decode` for a well-formed plain chunk whose header has the layout :func:`encode`
    writes (any sender's may, byte for byte), without parsing the JSON or re-checking the
    metadata of a stream's every chunk. Returns None for anything else, or on any defect, and
    decode_message then parses, checks and reports as usual: same result, same errors."""
    if len(frames) < 2:
        return None
    h = frames[0]
    hb = h if type(h) is bytes else getattr(h, "bytes", None)  # zmq.Frame: .bytes is cheap
    if type(hb) is not bytes or len(hb) > MAX_HEADER_BYTES:
        return None
    m = _HEADER_RE.fullmatch(hb)
    if m is None:
        return None
    src, seq, trace, t_sent, tail, stamp, frame_id = m.groups()
    plan = _PLANS.get(tail, _PLANS)
    if plan is _PLANS:
        if len(tail) > _TAIL_MAX:
            return None  # not cached: the cache holds at most _PLANS_MAX x _TAIL_MAX bytes
        plan = _plan(tail)
        if len(_PLANS) >= _PLANS_MAX:
            _PLANS.clear()
        _PLANS[tail] = plan
    if plan is None:
        return None
    n, names, specs, packed = plan
    if max_points is not None and n > max_points:
        return None
    if packed:  # one data frame: the arrays at their offsets (docs/wire-format.md "Packed chunks")
        if len(frames) != 2:
            return None
        f = frames[1]
        t = type(f)
        if (t is not bytes and t is not _Frame) or len(f) != packed:
            return None
        arrays = [np.ndarray(shape, dt, f, off) for dt, shape, off in specs]
    else:
        if len(frames) != 1 + len(specs):
            return None
        arrays = []
        for f, (dt, shape, nbytes) in zip(frames[1:], specs):
            t = type(f)
            if (t is not bytes and t is not _Frame) or len(f) != nbytes:  # len: bytes of either
                return None
            arrays.append(np.ndarray(shape, dt, f))  # a Frame exports its buffer: no memoryview needed
    # positional, in PointChunk's field order (about half the cost of keywords)
    chans = {names[0]: arrays[1]} if len(names) == 1 else dict(zip(names, arrays[1:]))
    return PointChunk(arrays[0], chans, src.decode("ascii"), int(seq), int(trace),
                      int(t_sent), time.monotonic_ns(), int(stamp) if stamp is not None else 0,
                      frame_id.decode("ascii") if frame_id else "")


def _plan(tail: bytes) -> Any:
    """What the header part ``tail`` (``"n":...`` up to the channel list) promises, checked
    as decode_message checks it; None unless it is a plain chunk that passes every check."""
    try:
        h = json.loads(b"{" + tail + b"}")
    except Exception:  # noqa: BLE001 - not JSON, too deeply nested, ...: the slow path reports it
        return None
    if not isinstance(h, dict) or not h.keys() <= _PLAIN_KEYS:
        return None  # codec, link, repeated keys, ...: the slow path decides
    n = h.get("n")
    chans = h.get("channels", [])
    pos_meta = h.get("positions")
    if (not isinstance(n, int) or isinstance(n, bool) or n < 0 or not isinstance(chans, list)
            or not isinstance(pos_meta, dict) or pos_meta.get("shape") != [n, 3]
            or pos_meta.get("dtype") not in ("float32", "float64")):
        return None
    try:
        specs = [("", *_frame_spec(pos_meta["dtype"], [n, 3], "positions"))]
        for i, meta in enumerate(chans):
            if not isinstance(meta, dict) or not isinstance(meta.get("name"), str):
                return None
            shape = meta.get("shape")
            if not isinstance(shape, list) or not shape or shape[0] != n:
                return None
            specs.append((meta["name"], *_frame_spec(meta.get("dtype"), shape, "")))
    except ChunkError:
        return None
    names = tuple(s[0] for s in specs[1:])
    if len(set(names)) != len(names):
        return None  # a repeated channel name: decode_message keeps the last one
    packed = h.get("packed", False)
    if packed is False:
        return n, names, tuple(s[1:] for s in specs), 0
    if packed is not True:
        return None
    offsets, total = _packed_offsets([s[3] for s in specs])
    if not total:
        return None  # nothing to pack (n = 0): decode_message
    return n, names, tuple((dt, shape, off) for (_, dt, shape, _), off in zip(specs, offsets)), total


def decode_message(frames: Sequence[Any], max_points: int | None = None) -> tuple[PointChunk, dict]:
    """:func:`decode`, also returning the parsed header (for its ``link`` object)."""
    if len(frames) < 2:
        raise ChunkError("bad_frame_count", f"expected a header and a positions frame, got {len(frames)} frame(s)")
    hbuf = _buf(frames[0])
    if hbuf.nbytes > MAX_HEADER_BYTES:
        raise ChunkError("bad_header", f"header of {hbuf.nbytes} bytes exceeds {MAX_HEADER_BYTES}")
    try:
        header = json.loads(bytes(hbuf))
    except (UnicodeDecodeError, ValueError) as exc:
        raise ChunkError("bad_header", f"header is not JSON: {exc}") from None
    if not isinstance(header, dict) or header.get("schema") != SCHEMA:
        raise ChunkError("bad_schema", f"header schema must be {SCHEMA!r}")
    n = header.get("n")
    if not isinstance(n, int) or isinstance(n, bool) or n < 0:
        raise ChunkError("bad_count", f"point count must be a non-negative integer, got {n!r}")
    if max_points is not None and n > max_points:
        raise ChunkError("too_large", f"chunk has {n} points, more than the configured maximum {max_points}")
    chans = header.get("channels", [])
    pos_meta = header.get("positions")
    if not isinstance(chans, list) or not isinstance(pos_meta, dict):
        raise ChunkError("bad_header", "header needs a 'positions' object and a 'channels' list")
    codec = header.get("codec")
    packed = header.get("packed", False)
    if packed is not False:
        if packed is not True:
            raise ChunkError("bad_header", f"'packed' must be true when present, got {packed!r}")
        if codec is not None:
            raise ChunkError("bad_header", "'packed' is not defined together with a 'codec'")
        if len(frames) != 2:
            raise ChunkError("bad_frame_count", f"a packed chunk is a header and one data frame, got {len(frames)} frame(s)")
        frames = [frames[0], *_unpack(frames[1], n, pos_meta, chans)]
    if len(frames) != 2 + len(chans):
        raise ChunkError("bad_frame_count", f"header lists {len(chans)} channel(s) but message has {len(frames) - 2} data frame(s)")
    if pos_meta.get("shape") != [n, 3]:
        raise ChunkError("bad_header", f"positions shape must be [{n}, 3], got {pos_meta.get('shape')!r}")
    shuffled = header.get("shuffle") is True
    if shuffled and codec is None:
        raise ChunkError("bad_header", "'shuffle' is only defined together with a 'codec'")
    quantised = pos_meta.get("dtype") == "int32" and "resolution" in pos_meta
    if pos_meta.get("dtype") not in ("float32", "float64") and not quantised:
        raise ChunkError("bad_dtype", f"positions must be float32 or float64 (or int32 with origin and resolution), got {pos_meta.get('dtype')!r}")
    positions = _array(frames[1], pos_meta["dtype"], [n, 3], "positions", codec, shuffled)
    if quantised:
        from .codec import dequantise

        positions = dequantise(positions, pos_meta.get("origin"), pos_meta.get("resolution"))
    channels: dict[str, np.ndarray] = {}
    for i, meta in enumerate(chans):
        if not isinstance(meta, dict) or not isinstance(meta.get("name"), str):
            raise ChunkError("bad_header", f"channel {i} needs a name")
        name = meta["name"]
        shape = meta.get("shape")
        if not isinstance(shape, list) or not shape or shape[0] != n:
            raise ChunkError("length_mismatch", f"channel {name!r} has shape {shape!r}, expected first dimension {n}")
        channels[name] = _array(frames[2 + i], meta.get("dtype"), shape, f"channel {name!r}", codec, shuffled)
    src = header.get("source", "")
    return PointChunk(
        positions=positions,
        channels=channels,
        source_id=src if isinstance(src, str) else "",
        seq=_header_int(header, "seq"),
        trace_id=_header_int(header, "trace"),
        t_sent_ns=_header_int(header, "t_sent_ns"),
        t_recv_ns=time.monotonic_ns(),
        stamp_ns=_header_int(header, "stamp_ns"),
        frame_id=_header_frame(header),
    ), header


def _unpack(frame: Any, n: int, pos_meta: dict, chans: list) -> list[memoryview]:
    """The arrays of a packed data frame as views (docs/wire-format.md "Packed chunks"), after
    the checks decode_message makes of separate frames."""
    specs = [_frame_spec(pos_meta.get("dtype"), [n, 3], "positions")]
    for i, meta in enumerate(chans):
        if not isinstance(meta, dict) or not isinstance(meta.get("name"), str):
            raise ChunkError("bad_header", f"channel {i} needs a name")
        shape = meta.get("shape")
        if not isinstance(shape, list) or not shape or shape[0] != n:
            raise ChunkError("length_mismatch", f"channel {meta['name']!r} has shape {shape!r}, expected first dimension {n}")
        specs.append(_frame_spec(meta.get("dtype"), shape, f"channel {meta['name']!r}"))
    nbytes = [nb for _, _, nb in specs]
    offsets, total = _packed_offsets(nbytes)
    mv = _buf(frame).cast("B")
    if mv.nbytes != total:
        raise ChunkError("truncated" if mv.nbytes < total else "size_mismatch",
                         f"packed data frame: header promises {total} bytes (positions and {len(chans)} channel(s), "
                         f"each at a multiple of {PACK_ALIGN} bytes), frame has {mv.nbytes}")
    return [mv[off:off + nb] for off, nb in zip(offsets, nbytes)]


def _header_int(header: dict, key: str) -> int:
    v = header.get(key, 0)
    return v if isinstance(v, int) and not isinstance(v, bool) else 0


def _header_frame(header: dict) -> str:
    f = header.get("frame", "")
    return f if isinstance(f, str) else ""
