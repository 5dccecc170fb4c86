"""Layout of the ring's per-slot arrays and the shared-memory segment helper.

The ring segment and both slabs use the *same* array layout (``array_specs``), so a
snapshot is a set of range copies between identically shaped arrays.
"""
from __future__ import annotations

import hashlib
import json
import mmap
import os
import re
import secrets
from dataclasses import dataclass, field
from typing import Any, Sequence

from ..errors import Error

import numpy as np

SHM_DIR = "/dev/shm"
_NAME_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,200}$")
ALIGN = 64


class RingError(Error):
    """Base class of ring errors."""


class RingConfigError(RingError, ValueError):
    """The ring was configured with invalid parameters."""


class RingAttachError(RingError):
    """A segment could not be attached (missing, wrong magic/version/layout)."""


@dataclass(frozen=True)
class ChannelSpec:
    """A stored per-point channel. Convention: ``rgb`` is uint8 width 3; others float32 width 1."""

    name: str
    dtype: str = "float32"
    width: int = 1

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name or not _NAME_RE.match(self.name):
            raise RingConfigError(f"bad channel name {self.name!r}")
        try:
            np.dtype(self.dtype)
        except TypeError as e:
            raise RingConfigError(f"channel {self.name!r}: bad dtype {self.dtype!r}") from e
        if int(self.width) < 1:
            raise RingConfigError(f"channel {self.name!r}: width must be >= 1")

    @classmethod
    def default(cls, name: str) -> "ChannelSpec":
        if name == "rgb":
            return cls("rgb", "uint8", 3)
        return cls(name, "float32", 1)

    @classmethod
    def coerce(cls, c: "ChannelSpec | str") -> "ChannelSpec":
        if isinstance(c, ChannelSpec):
            return c
        if isinstance(c, str):
            return cls.default(c)
        if isinstance(c, dict):
            return cls(**c)
        raise RingConfigError(f"channel must be a ChannelSpec or a name, got {c!r}")

    def to_dict(self) -> dict:
        return {"name": self.name, "dtype": np.dtype(self.dtype).name, "width": int(self.width)}


#: names that are built in and cannot be used as channel names
RESERVED = frozenset({"positions", "t_ingest_ms", "importance", "generation"})


@dataclass(frozen=True)
class RingLayout:
    """Capacity + stored channels (+ free flag bits). Picklable; ``to_dict``/``from_dict``."""

    capacity: int
    channels: tuple[ChannelSpec, ...] = field(default_factory=tuple)
    flags: int = 0

    def __post_init__(self):
        if isinstance(self.capacity, bool) or not isinstance(self.capacity, (int, np.integer)) or int(self.capacity) < 1:
            raise RingConfigError(f"max_points must be an integer >= 1, got {self.capacity!r}")
        object.__setattr__(self, "capacity", int(self.capacity))
        chans = tuple(ChannelSpec.coerce(c) for c in self.channels)
        names = [c.name for c in chans]
        if len(set(names)) != len(names):
            raise RingConfigError(f"duplicate channel names in {names}")
        bad = RESERVED.intersection(names)
        if bad:
            raise RingConfigError(f"channel names {sorted(bad)} are built in")
        object.__setattr__(self, "channels", chans)

    def to_dict(self) -> dict:
        return {"capacity": self.capacity, "channels": [c.to_dict() for c in self.channels], "flags": int(self.flags)}

    @classmethod
    def from_dict(cls, d: dict) -> "RingLayout":
        return cls(int(d["capacity"]), tuple(ChannelSpec(**c) for c in d.get("channels", ())), int(d.get("flags", 0)))

    def fingerprint(self) -> int:
        """A stable 63-bit hash of the layout (stored in segment headers)."""
        blob = json.dumps(self.to_dict(), sort_keys=True).encode()
        return int.from_bytes(hashlib.blake2b(blob, digest_size=8).digest(), "little") & ((1 << 63) - 1)


def array_specs(layout: RingLayout) -> list[tuple[str, np.dtype, tuple[int, ...]]]:
    """(key, dtype, shape) of every per-slot array, in storage order.

    Keys: ``positions`` (cap,3) f32 offsets from origin; ``t_ingest_ms`` f64; ``importance``
    f32; ``generation`` u32 (stamp of the slot's occupant: the low 32 bits of the ring's push
    counter, see ``pointflow.ring.ring.GEN_MASK``); ``ch:<name>`` channel values and
    ``gen:<name>`` u32 (stamp of the occupant the value was written for).
    """
    cap = layout.capacity
    out: list[tuple[str, np.dtype, tuple[int, ...]]] = [
        ("positions", np.dtype(np.float32), (cap, 3)),
        ("t_ingest_ms", np.dtype(np.float64), (cap,)),
        ("importance", np.dtype(np.float32), (cap,)),
        ("generation", np.dtype(np.uint32), (cap,)),
    ]
    for c in layout.channels:
        shape = (cap,) if c.width == 1 else (cap, c.width)
        out.append(("ch:" + c.name, np.dtype(c.dtype), shape))
        out.append(("gen:" + c.name, np.dtype(np.uint32), (cap,)))
    return out


def _align(x: int) -> int:
    return (x + ALIGN - 1) // ALIGN * ALIGN


def data_size(layout: RingLayout) -> int:
    off = 0
    for _, dt, shape in array_specs(layout):
        off = _align(off) + dt.itemsize * int(np.prod(shape))
    return _align(off)


def map_arrays(buf, base: int, layout: RingLayout) -> dict[str, np.ndarray]:
    arrays = {}
    off = 0
    for key, dt, shape in array_specs(layout):
        off = _align(off)
        arrays[key] = np.ndarray(shape, dtype=dt, buffer=buf, offset=base + off)
        off += dt.itemsize * int(np.prod(shape))
    return arrays


def new_name(prefix: str) -> str:
    """An unguessable segment name (128 random bits)."""
    return f"{prefix}_{secrets.token_hex(16)}"


def check_name(name: str) -> str:
    if not isinstance(name, str) or not _NAME_RE.match(name) or name.startswith("."):
        raise RingAttachError(f"invalid segment name {name!r}")
    return name


class Segment:
    """A POSIX shared-memory segment (a file under /dev/shm) mapped read/write.

    Created with O_EXCL and mode 0600; the file descriptor stays open so ``flock`` can
    be taken on it (released by the kernel if the holder dies).
    """

    def __init__(self, name: str, size: int | None = None, create: bool = False):
        check_name(name)
        self.name = name
        self.path = os.path.join(SHM_DIR, name)
        self.owner = create
        self.owner_pid = os.getpid()
        flags = os.O_RDWR | getattr(os, "O_CLOEXEC", 0)
        if create:
            fd = os.open(self.path, flags | os.O_CREAT | os.O_EXCL, 0o600)
            try:
                os.fchmod(fd, 0o600)
                os.ftruncate(fd, int(size))
            except BaseException:
                os.close(fd)
                os.unlink(self.path)
                raise
        else:
            try:
                fd = os.open(self.path, flags)
            except FileNotFoundError:
                raise RingAttachError(f"no shared-memory segment named {name!r}") from None
            except PermissionError:
                raise RingAttachError(f"segment {name!r} is not accessible (owner-only permissions)") from None
            size = os.fstat(fd).st_size
            if size == 0:
                os.close(fd)
                raise RingAttachError(f"segment {name!r} is empty (not initialised)")
        self.fd = fd
        self.size = int(size)
        try:
            self.mm = mmap.mmap(fd, self.size)
        except BaseException:
            os.close(fd)
            if create:
                os.unlink(self.path)
            raise

    def close(self) -> None:
        mm, self.mm = getattr(self, "mm", None), None
        if mm is not None:
            try:
                mm.close()
            except BufferError:
                pass  # numpy views still alive; the mapping goes when they do
        fd, self.fd = getattr(self, "fd", -1), -1
        if fd is not None and fd >= 0:
            try:
                os.close(fd)
            except OSError:
                pass

    def unlink(self) -> None:
        if self.owner and os.getpid() == self.owner_pid:
            try:
                os.unlink(self.path)
            except FileNotFoundError:
                pass


def _finalize_segment(seg: Segment, unlink: bool) -> None:
    try:
        if unlink:
            seg.unlink()
    finally:
        seg.close()


def dumps_json(obj: Any) -> bytes:
    return json.dumps(obj, sort_keys=True, separators=(",", ":")).encode()


def as_channel_specs(channels: Sequence[ChannelSpec | str]) -> tuple[ChannelSpec, ...]:
    return tuple(ChannelSpec.coerce(c) for c in channels)
