"""ZeroMQ handoff of double-buffered slabs: cadence (SlabWriter) -> render (SlabReader).

Sockets (created by the caller): ready = PUSH (cadence, connects) -> PULL (render, binds);
release = PUSH (render, connects) -> PULL (cadence, binds). Message formats: docs/ring.md.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field

import numpy as np
import zmq

from .ring import PointRing, _merge_ranges
from .slabs import S_EPOCH, S_HEAD, S_HELD, S_ORIGIN_SET, S_SEQ, S_SIZE, S_T_SNAPSHOT, S_WRITES, SlabPair, SlabView

HANDOFF_TAG = b"pf.ring.handoff/1"
RELEASE_TAG = b"pf.ring.release/1"
RANGE_BLOCK = 16384  # slots per block of the incrementally maintained channel min/max


@dataclass
class Handoff:
    seq: int
    slab: int
    count: int
    head: int
    capacity: int
    origin: tuple[float, float, float]
    dirty: list[tuple[int, int]] | None  # half-open slot ranges changed since the previous handoff; None = full
    epoch_ns: int = 0
    t_snapshot_ns: int = 0
    channel_ranges: dict[str, tuple[float, float]] = field(default_factory=dict)
    trace_ids: list[int] = field(default_factory=list)  # chunks first visible in this snapshot
    extra: dict = field(default_factory=dict)
    t_commit_ns: list[int] = field(default_factory=list)  # commit time of each trace id (same order)

    def encode(self) -> list[bytes]:
        meta = {"seq": self.seq, "slab": self.slab, "count": self.count, "head": self.head,
                "capacity": self.capacity, "origin": [float(x) for x in self.origin],
                "epoch_ns": self.epoch_ns, "t_snapshot_ns": self.t_snapshot_ns,
                "dirty_full": self.dirty is None,
                "channel_ranges": {k: [float(a), float(b)] for k, a_b in self.channel_ranges.items() for a, b in [a_b]},
                "extra": self.extra or {}}
        dirty = np.asarray(self.dirty if self.dirty else np.zeros((0, 2)), dtype="<i8").reshape(-1, 2)
        tids = np.asarray(self.trace_ids, dtype="<u8")
        tcs = np.asarray(self.t_commit_ns, dtype="<i8")
        return [HANDOFF_TAG, json.dumps(meta, separators=(",", ":")).encode(), dirty.tobytes(), tids.tobytes(),
                tcs.tobytes()]

    @classmethod
    def decode(cls, frames) -> "Handoff":
        frames = [bytes(f) for f in frames]
        if len(frames) < 4 or frames[0] != HANDOFF_TAG:
            raise ValueError("not a pointflow ring handoff message")
        meta = json.loads(frames[1])
        dirty = None
        if not meta["dirty_full"]:
            d = np.frombuffer(frames[2], dtype="<i8").reshape(-1, 2)
            dirty = [(int(a), int(b)) for a, b in d]
        tids = [int(x) for x in np.frombuffer(frames[3], dtype="<u8")]
        tcs = [int(x) for x in np.frombuffer(frames[4], dtype="<i8")] if len(frames) > 4 else []
        return cls(seq=int(meta["seq"]), slab=int(meta["slab"]), count=int(meta["count"]), head=int(meta["head"]),
                   capacity=int(meta["capacity"]), origin=tuple(float(x) for x in meta["origin"]), dirty=dirty,
                   epoch_ns=int(meta["epoch_ns"]), t_snapshot_ns=int(meta["t_snapshot_ns"]),
                   channel_ranges={k: (float(v[0]), float(v[1])) for k, v in meta["channel_ranges"].items()},
                   trace_ids=tids, extra=meta.get("extra") or {}, t_commit_ns=tcs)


def _union(a, b):
    """Union of two dirty lists (None = full)."""
    if a is None or b is None:
        return None
    return _merge_ranges(list(a) + list(b))


def _encode_release(slab: int, seq: int) -> list[bytes]:
    return [RELEASE_TAG, np.array([slab, seq], dtype="<i8").tobytes()]


class SlabWriter:
    """Cadence side: snapshot the ring into the slab the renderer does not hold, then hand it over.

    Which slabs are handed out (and with which seq) is stored in the slab headers, so a restarted
    cadence process picks up where the crashed one left off (it sends a full handoff next).
    """

    def __init__(self, ring: PointRing, slabs: SlabPair, ready_sock: zmq.Socket, release_sock: zmq.Socket):
        if slabs.layout.fingerprint() != ring.layout.fingerprint():
            raise ValueError("ring and slabs have different layouts")
        self.ring = ring
        self.slabs = slabs
        self.ready = ready_sock
        self.release_sock = release_sock
        self._held = [int(slabs.state(i)[S_HELD]) for i in (0, 1)]  # seq handed out and not released, 0 = free
        self._seq = max(int(slabs.state(i)[S_SEQ]) for i in (0, 1))
        #: Handoffs up to this seq were made by an earlier writer (a cadence that died).
        self.inherited_seq = self._seq
        self._pending: list = [None, None]  # ranges each slab lacks; None = needs a full copy
        self._carry: list | None = None  # dirty of handoffs that could not be sent
        self._force_full = True
        self._last_written: int | None = None
        # channel range bookkeeping
        lay = ring.layout
        self._range_keys = ["importance"] + [c.name for c in lay.channels
                                             if c.width == 1 and np.dtype(c.dtype).kind == "f"]
        nb = (lay.capacity + RANGE_BLOCK - 1) // RANGE_BLOCK
        self._bmin = {k: np.full(nb, np.inf) for k in self._range_keys}
        self._bmax = {k: np.full(nb, -np.inf) for k in self._range_keys}
        self.stats = {"published": 0, "skipped_busy": 0, "full_copies": 0, "copied_slots": 0, "send_again": 0}

    # -------------------------------------------------------------- renderer bookkeeping
    @property
    def held(self) -> tuple[bool, bool]:
        return (self._held[0] != 0, self._held[1] != 0)

    def poll_releases(self) -> int:
        """Process pending release messages (non-blocking); returns how many freed a slab."""
        n = 0
        while True:
            try:
                frames = self.release_sock.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return n
            if len(frames) != 2 or bytes(frames[0]) != RELEASE_TAG or len(frames[1]) != 16:
                continue
            slab, seq = (int(x) for x in np.frombuffer(bytes(frames[1]), dtype="<i8"))
            if slab in (0, 1) and self._held[slab] == seq and seq != 0:  # stale releases are ignored
                self._held[slab] = 0
                self.slabs.state(slab)[S_HELD] = 0
                n += 1

    def resync(self, last_seq: int) -> int:
        """The renderer holds no slab and the newest handoff it received is ``last_seq``:
        free every slab handed out up to ``last_seq`` (it has seen them) or by an earlier
        writer (their releases died with it: a frozen cadence replaced as hung never reads
        the releases queued to it). A slab handed out later is in flight and stays held.
        Returns how many slabs this freed."""
        self.poll_releases()
        n = 0
        for i in (0, 1):
            s = self._held[i]
            if s and (s <= last_seq or s <= self.inherited_seq):
                self._held[i] = 0
                self.slabs.state(i)[S_HELD] = 0
                n += 1
        return n

    def free_lost(self, last_seq: int, slabs: tuple[int, ...] = (0, 1)) -> int:
        """The renderer holds no slab and the newest handoff it received is ``last_seq``, yet
        a slab among ``slabs`` (the caller's: those handed out long enough ago) is held with
        a later handoff: it never arrived (sent into the connection of a renderer that died,
        or before a hello that never came). Free it, and send the next handoff full: the
        renderer missed that handoff's changes. Returns how many slabs this freed."""
        self.poll_releases()
        n = 0
        for i in slabs:
            s = self._held[i]
            if s and s > last_seq:
                self._held[i] = 0
                self.slabs.state(i)[S_HELD] = 0
                n += 1
        if n:
            self._force_full = True
        return n

    def reset_reader(self) -> None:
        """The renderer restarted: consider both slabs free and send a full handoff next."""
        self._held = [0, 0]
        for i in (0, 1):
            self.slabs.state(i)[S_HELD] = 0
        self._force_full = True

    # -------------------------------------------------------------- publish
    def publish(self, extra: dict | None = None) -> Handoff | None:
        """Snapshot into a free slab and send the handoff; None when the renderer holds both slabs.

        Publishes even when nothing changed (``dirty == []``) so the renderer can redraw.
        """
        self.poll_releases()
        free = [i for i in (0, 1) if self._held[i] == 0]
        if not free:
            self.stats["skipped_busy"] += 1
            return None
        # the slab written most recently lacks the least
        x = self._last_written if self._last_written in free else free[0]
        ring, slabs = self.ring, self.slabs
        with ring.lock():
            ch = ring.take_changes()
            for i in (0, 1):
                self._pending[i] = _union(self._pending[i], ch.dirty)
            self.copy_to_slab(x, self._pending[x])
            hs = ring.header_state()
            t_snap = time.monotonic_ns()
        self._pending[x] = []
        self._last_written = x
        dirty = None if self._force_full else _union(self._carry, ch.dirty)
        self._carry = []
        ranges = self._update_ranges(x, dirty, hs["head"], hs["size"])
        self._seq += 1
        seq = self._seq
        st = slabs.state(x)
        st[S_HEAD] = hs["head"]
        st[S_SIZE] = hs["size"]
        st[S_EPOCH] = hs["epoch_ns"]
        st[S_WRITES] = hs["write_count"]
        st[S_T_SNAPSHOT] = t_snap
        st[S_ORIGIN_SET] = int(hs["origin_set"])
        slabs.origin_array(x)[:] = hs["origin"]
        st[S_SEQ] = seq
        st[S_HELD] = seq
        self._held[x] = seq
        h = Handoff(seq=seq, slab=x, count=hs["size"], head=hs["head"], capacity=ring.capacity,
                    origin=tuple(float(v) for v in hs["origin"]), dirty=dirty, epoch_ns=hs["epoch_ns"],
                    t_snapshot_ns=t_snap, channel_ranges=ranges, trace_ids=[t for t, _ in ch.commits],
                    extra=dict(extra or {}), t_commit_ns=[c for _, c in ch.commits])
        if ch.commits_lost:
            h.extra.setdefault("trace_ids_lost", True)
        try:
            self.ready.send_multipart(h.encode(), zmq.NOBLOCK)
        except zmq.Again:
            # nobody to take it: the slab stays free and its changes ride on the next handoff
            self._held[x] = 0
            st[S_HELD] = 0
            self._carry = dirty if self._force_full is False else None
            self.stats["send_again"] += 1
            return None
        self._force_full = False
        self.stats["published"] += 1
        return h

    def copy_to_slab(self, x: int, ranges: list[tuple[int, int]] | None) -> None:
        """Copy ring slots (all when ``ranges`` is None) into slab ``x``. Caller holds the ring lock."""
        dst = self.slabs.arrays(x)
        src = self.ring.arrays
        if ranges is None:
            for k, arr in src.items():
                np.copyto(dst[k], arr)
            self.stats["full_copies"] += 1
            self.stats["copied_slots"] += self.ring.capacity
        else:
            for a, b in ranges:
                for k, arr in src.items():
                    dst[k][a:b] = arr[a:b]
                self.stats["copied_slots"] += b - a

    def _update_ranges(self, x: int, dirty, head: int, size: int) -> dict[str, tuple[float, float]]:
        """Exact min/max over occupied slots with the value present, maintained per block of
        RANGE_BLOCK slots: only blocks touched by the dirty ranges are recomputed."""
        cap = self.ring.capacity
        nb = len(self._bmin["importance"])
        if dirty is None:
            blocks = range(nb)
        else:
            bs = set()
            for a, b in dirty:
                bs.update(range(a // RANGE_BLOCK, (b - 1) // RANGE_BLOCK + 1))
            blocks = sorted(bs)
        if blocks:
            arrs = self.slabs.arrays(x)
            gen = arrs["generation"]
            for bi in blocks:
                s0, s1 = bi * RANGE_BLOCK, min(cap, (bi + 1) * RANGE_BLOCK)
                occ = None if size == cap else ((np.arange(s0, s1) - head) % cap) < size
                for k in self._range_keys:
                    if k == "importance":
                        v = arrs["importance"][s0:s1]
                        m = occ
                    else:
                        v = arrs["ch:" + k][s0:s1]
                        m = arrs["gen:" + k][s0:s1] == gen[s0:s1]
                        if occ is not None:
                            m &= occ
                    vv = v if m is None else v[m]
                    if vv.size:
                        self._bmin[k][bi] = np.fmin.reduce(vv)
                        self._bmax[k][bi] = np.fmax.reduce(vv)
                    else:
                        self._bmin[k][bi] = np.inf
                        self._bmax[k][bi] = -np.inf
        out = {}
        for k in self._range_keys:
            lo, hi = float(self._bmin[k].min()), float(self._bmax[k].max())
            if np.isfinite(lo) and np.isfinite(hi):
                out[k] = (lo, hi)
        return out


class SlabReader:
    """Render side: receive handoffs, hold at most one slab, give it back with :meth:`release`.

    If several handoffs are queued, :meth:`recv` returns the newest, releases the skipped slabs
    at once and merges their dirty ranges and trace ids into the returned handoff.
    """

    def __init__(self, slabs: SlabPair, ready_sock: zmq.Socket, release_sock: zmq.Socket):
        self.slabs = slabs
        self.ready = ready_sock
        self.release_sock = release_sock
        self._held: tuple[int, int] | None = None  # (slab, seq)
        #: Newest handoff received, and when (monotonic ns): the renderer's resync says so.
        self.last_seq = 0
        self.t_last_ns = time.monotonic_ns()

    @property
    def held(self) -> int | None:
        return None if self._held is None else self._held[0]

    def _send_release(self, slab: int, seq: int) -> None:
        try:
            self.release_sock.send_multipart(_encode_release(slab, seq), zmq.NOBLOCK)
        except zmq.Again:
            pass  # cadence gone: the restarted cadence reads held slabs from the slab headers

    def recv(self, timeout_ms: int = 0) -> tuple[Handoff, SlabView] | None:
        if not self.ready.poll(timeout_ms, zmq.POLLIN):
            return None
        msgs = [Handoff.decode(self.ready.recv_multipart())]
        while self.ready.poll(0, zmq.POLLIN):
            msgs.append(Handoff.decode(self.ready.recv_multipart()))
        # a handoff whose slab carries a newer seq came so late that the cadence took it for
        # lost and wrote that slab again (SlabWriter.free_lost): it is not ours to read
        msgs = [m for m in msgs if int(self.slabs.state(m.slab)[S_SEQ]) == m.seq]
        if not msgs:
            return None
        h = msgs[-1]
        if len(msgs) > 1:
            dirty: list | None = []
            tids, tcs = [], []
            for m in msgs:
                dirty = _union(dirty, m.dirty)
                tids += m.trace_ids
                tcs += m.t_commit_ns
            h.dirty, h.trace_ids, h.t_commit_ns = dirty, tids, tcs
            for m in msgs[:-1]:
                if m.slab != h.slab:
                    self._send_release(m.slab, m.seq)
        if self._held is not None and self._held[0] != h.slab:
            self._send_release(*self._held)
        self._held = (h.slab, h.seq)
        self.last_seq = max(self.last_seq, h.seq)
        self.t_last_ns = time.monotonic_ns()
        return h, self.slabs.slab_view(h.slab)

    def release(self, slab_id: int | None = None) -> None:
        """Give the held slab back (``slab_id`` must be the held one, or None for whichever is held)."""
        if self._held is None:
            return
        if slab_id is not None and slab_id != self._held[0]:
            return
        self._send_release(*self._held)
        self._held = None
