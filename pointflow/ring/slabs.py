"""Double-buffered snapshot slabs (A/B) in shared memory.

A slab holds the ring's per-slot arrays in **slot order** (the same layout as the ring),
so a dirty slot range maps 1:1 to a GPU buffer range.
"""
from __future__ import annotations

import json
import os
import weakref
from dataclasses import dataclass

import numpy as np

from .layout import RingAttachError, RingLayout, Segment, _finalize_segment, data_size, dumps_json, map_arrays, new_name

SLAB_MAGIC = b"PFSLAB\x00\x01"
SLAB_VERSION = 2
SLAB_HEADER = 4096
_S_STATE_OFF, _S_NSTATE = 64, 32
_S_FSTATE_OFF = 320  # float64[4]: origin xyz
_S_LAYOUT_OFF = 512  # layout json up to SLAB_HEADER
(S_SEQ, S_HEAD, S_SIZE, S_EPOCH, S_WRITES, S_CAP, S_FINGERPRINT, S_HELD, S_OWNER_PID, S_T_SNAPSHOT,
 S_ORIGIN_SET) = range(11)


@dataclass
class SlabView:
    """numpy views of one slab (valid while the reader holds the slab).

    ``valid`` is the per-slot occupancy mask (computed from head/size); a channel value
    is present for a slot iff ``channel_generation[name] == generation`` and the slot is
    valid (see :meth:`channel_present`).
    """

    slab: int
    seq: int
    head: int
    size: int
    capacity: int
    origin: np.ndarray  # float64 (3,)
    epoch_ns: int
    write_count: int
    positions: np.ndarray  # (cap, 3) float32 offsets from origin
    t_ingest_ms: np.ndarray
    importance: np.ndarray
    generation: np.ndarray
    channels: dict[str, np.ndarray]
    channel_generation: dict[str, np.ndarray]

    @property
    def valid(self) -> np.ndarray:
        idx = np.arange(self.capacity)
        return ((idx - self.head) % self.capacity) < self.size

    def logical_slots(self) -> np.ndarray:
        s = np.arange(self.head, self.head + self.size)
        return s % self.capacity if self.head + self.size > self.capacity else s

    def channel_present(self, name: str) -> np.ndarray:
        return (self.channel_generation[name] == self.generation) & self.valid

    def world_positions(self, logical: bool = True) -> np.ndarray:
        p = self.positions[self.logical_slots()] if logical else self.positions
        return p.astype(np.float64) + self.origin


class SlabPair:
    """Two shared-memory slabs for one ring layout. ``create`` owns (unlinks on close); ``attach`` does not."""

    def __init__(self, layout: RingLayout, segs: list[Segment]):
        self.layout = layout
        self._segs = segs
        self._finalizers = [weakref.finalize(self, _finalize_segment, s, s.owner) for s in segs]
        self._arrays = [map_arrays(s.mm, SLAB_HEADER, layout) for s in segs]
        self._st = [np.ndarray((_S_NSTATE,), np.int64, buffer=s.mm, offset=_S_STATE_OFF) for s in segs]
        self._fst = [np.ndarray((4,), np.float64, buffer=s.mm, offset=_S_FSTATE_OFF) for s in segs]
        self._closed = False

    @classmethod
    def create(cls, layout: RingLayout) -> "SlabPair":
        blob = dumps_json(layout.to_dict())
        if _S_LAYOUT_OFF + len(blob) > SLAB_HEADER:
            raise ValueError("layout too large for the slab header")
        base = new_name("pfslab")
        segs: list[Segment] = []
        try:
            for suffix in ("a", "b"):
                segs.append(Segment(f"{base}_{suffix}", SLAB_HEADER + data_size(layout), create=True))
        except BaseException:
            for s in segs:
                _finalize_segment(s, True)
            raise
        for s in segs:
            mm = s.mm
            mm[16:20] = len(blob).to_bytes(4, "little")
            mm[_S_LAYOUT_OFF:_S_LAYOUT_OFF + len(blob)] = blob
            st = np.ndarray((_S_NSTATE,), np.int64, buffer=mm, offset=_S_STATE_OFF)
            st[S_CAP] = layout.capacity
            st[S_FINGERPRINT] = layout.fingerprint()
            st[S_OWNER_PID] = os.getpid()
            del st
            mm[8:12] = SLAB_VERSION.to_bytes(4, "little")
            mm[0:8] = SLAB_MAGIC
        return cls(layout, segs)

    @classmethod
    def attach(cls, names: tuple[str, str], layout: RingLayout | None = None) -> "SlabPair":
        if len(names) != 2:
            raise RingAttachError("a slab pair has exactly two names")
        segs: list[Segment] = []
        try:
            lay = None
            for nm in names:
                s = Segment(nm, create=False)
                segs.append(s)
                mm = s.mm
                if s.size < SLAB_HEADER or bytes(mm[0:8]) != SLAB_MAGIC:
                    raise RingAttachError(f"segment {nm!r} is not a pointflow slab (bad magic)")
                ver = int.from_bytes(mm[8:12], "little")
                if ver != SLAB_VERSION:
                    raise RingAttachError(f"slab {nm!r} has version {ver}, expected {SLAB_VERSION}")
                n = int.from_bytes(mm[16:20], "little")
                try:
                    this = RingLayout.from_dict(json.loads(bytes(mm[_S_LAYOUT_OFF:_S_LAYOUT_OFF + n])))
                except Exception as e:  # noqa: BLE001
                    raise RingAttachError(f"slab {nm!r} has an unreadable layout: {e}") from None
                st = np.ndarray((_S_NSTATE,), np.int64, buffer=mm, offset=_S_STATE_OFF)
                fp = int(st[S_FINGERPRINT])
                del st
                if fp != this.fingerprint() or s.size != SLAB_HEADER + data_size(this):
                    raise RingAttachError(f"slab {nm!r}: header does not match its layout")
                if lay is not None and lay.fingerprint() != this.fingerprint():
                    raise RingAttachError("the two slabs have different layouts")
                lay = this
            if layout is not None and layout.fingerprint() != lay.fingerprint():
                raise RingAttachError(f"slabs have layout {lay.to_dict()}, expected {layout.to_dict()}")
        except BaseException:
            for s in segs:
                s.close()
            raise
        return cls(lay, segs)

    @property
    def names(self) -> tuple[str, str]:
        return (self._segs[0].name, self._segs[1].name)

    def arrays(self, i: int) -> dict[str, np.ndarray]:
        return self._arrays[i]

    def state(self, i: int) -> np.ndarray:
        """The slab's int64 header fields (S_* indices); used by the writer."""
        return self._st[i]

    def origin_array(self, i: int) -> np.ndarray:
        return self._fst[i][0:3]

    def slab_view(self, i: int) -> SlabView:
        a = self._arrays[i]
        st = self._st[i]
        chans = {c.name: a["ch:" + c.name] for c in self.layout.channels}
        cgen = {c.name: a["gen:" + c.name] for c in self.layout.channels}
        return SlabView(slab=i, seq=int(st[S_SEQ]), head=int(st[S_HEAD]), size=int(st[S_SIZE]),
                        capacity=self.layout.capacity, origin=self._fst[i][0:3].copy(), epoch_ns=int(st[S_EPOCH]),
                        write_count=int(st[S_WRITES]), positions=a["positions"], t_ingest_ms=a["t_ingest_ms"],
                        importance=a["importance"], generation=a["generation"], channels=chans,
                        channel_generation=cgen)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._arrays = []
        self._st = []
        self._fst = []
        for f in self._finalizers:
            f()

    def unlink(self) -> None:
        for s in self._segs:
            s.unlink()

    def __enter__(self) -> "SlabPair":
        return self

    def __reduce__(self):
        return (SlabPair.attach, (self.names,))

    def __exit__(self, *exc) -> None:
        self.close()
