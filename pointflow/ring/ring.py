"""PointRing: the bounded Structure-of-Arrays point store in shared memory.

See docs/ring.md for the layout and the exact eviction semantics.
"""
from __future__ import annotations

import fcntl
import json
import os
import threading
import time
import weakref
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from typing import Iterator, Sequence

import numpy as np

from .layout import (
    ChannelSpec,
    RingAttachError,
    RingConfigError,
    RingLayout,
    Segment,
    _finalize_segment,
    as_channel_specs,
    data_size,
    dumps_json,
    map_arrays,
    new_name,
)

MAGIC = b"PFRING\x00\x01"
VERSION = 2
#: The per-slot generation stamps (``generation``, ``gen:<channel>``) are the low 32 bits of
#: the push counter: 4 bytes per point and channel less to write than 64-bit stamps (about
#: 10 % of ingest's CPU per point at 10k-point chunks). They are only compared for equality
#: (a channel present, a picked slot unchanged); after 2**32 pushes the stamps repeat, and a
#: stale value could pass for present only in a slot left untouched for exactly 2**32 pushes.
GEN_MASK = 0xFFFFFFFF
K_CANDIDATES = 16  # importance eviction looks at the K oldest points

# ---- header layout (bytes) -------------------------------------------------------------
# 0:8 magic | 8:12 version u32 | 12:16 header size u32 | 16:20 config json length u32
# 24:32 data size u64 | 64:576 int64 state[64] | 576:640 float64 fstate[8]
# 1024:3072 dirty ranges int64[128,2] | 4096:8192 config json | 8192:24576 commit log int64[1024,2]
HEADER_SIZE = 32768
STATE_OFF, N_STATE = 64, 64
FSTATE_OFF, N_FSTATE = 576, 8
DIRTY_OFF, DIRTY_MAX = 1024, 128
CONFIG_OFF, CONFIG_MAX = 4096, 4096
COMMIT_OFF, COMMIT_N = 8192, 1024

(I_CAP, I_HEAD, I_SIZE, I_DROPPED, I_WRITES, I_GEN, I_EPOCH, I_ORIGIN_SET, I_DIRTY_N, I_DIRTY_FULL,
 I_COMMIT_COUNT, I_COMMIT_TAKEN, I_TOTAL_WRITTEN, I_RESETS, I_FINGERPRINT, I_OWNER_PID, I_LAST_PUSH_NS,
 I_ORIGIN_GEN, I_REJECTED) = range(19)

#: A point is stored only when its offset from the origin is below this on every axis: a
#: float32 offset below 2^24 has a spacing of at most 1, so it is stored with an error of at
#: most 0.5 units (and at most 2^-24 of the offset). Farther points are rejected
#: (``PushResult.rejected``, ingest's ``out_of_range``), so no offset is ever inf or overflows.
MAX_OFFSET = float(2 ** 24)
#: Only points with every |coordinate| at most this (2^53: float64 still resolves whole
#: units) take part in choosing the origin.
MAX_ORIGIN_ABS = float(2 ** 53)

_min, _max = np.minimum.reduce, np.maximum.reduce
#: per-push checks by identity (native float dtypes are singletons; comparing a dtype with a
#: type, or looking up ``np.integer``, costs a few hundred ns each on the hot path)
_F32, _F64 = np.dtype(np.float32), np.dtype(np.float64)
_INTS = (int, np.integer)

EVICTIONS = ("drop_oldest", "drop_newest", "importance")
_EVICTION_ALIASES = {"fifo": "drop_oldest", "drop_oldest": "drop_oldest", "drop_newest": "drop_newest",
                     "importance": "importance"}


@dataclass
class PushResult:
    written: int  # incoming points stored
    dropped: int  # points lost by this push (overwritten old ones + discarded incoming ones)
    #: incoming points not stored because they are not finite or too far from the origin
    #: (offset >= MAX_OFFSET on some axis); not part of ``dropped``
    rejected: int = 0


@dataclass
class RingStats:
    total_points: int
    dropped_points: int
    under_pressure: bool
    capacity: int
    head: int
    origin: tuple[float, float, float] | None
    epoch_ns: int
    write_count: int
    eviction: str = "drop_oldest"
    total_written: int = 0
    resets: int = 0
    rejected_points: int = 0  # out of range or not finite, since the last reset

    def to_dict(self) -> dict:
        d = asdict(self)
        d["origin"] = list(self.origin) if self.origin is not None else None
        return d


@dataclass
class Snapshot:
    """Ring content in logical order (oldest first); world positions in float64."""

    positions: np.ndarray  # (N, 3) float64 world coordinates
    channels: dict[str, np.ndarray]  # values; float channels hold NaN where missing
    present: dict[str, np.ndarray]  # per channel bool (N,): value written for this occupant
    t_ingest_ms: np.ndarray  # (N,) float64 ms since epoch
    importance: np.ndarray  # (N,) float32
    slots: np.ndarray  # (N,) int64 ring slot of each point
    generation: np.ndarray  # (N,) uint64
    origin: tuple[float, float, float] | None
    epoch_ns: int

    def __len__(self) -> int:
        return int(self.positions.shape[0])


@dataclass
class PointRecord:
    slot: int
    position: np.ndarray  # (3,) float64 world
    channels: dict[str, object]  # missing channels absent
    t_ingest_ms: float
    generation: int
    importance: float = 1.0


@dataclass
class TemporalStats:
    oldest_age_ms: float | None  # None when empty
    newest_age_ms: float | None
    count_in_window: int


@dataclass
class Changes:
    """What :meth:`PointRing.take_changes` hands the cadence (consumed once)."""

    dirty: list[tuple[int, int]] | None  # None = full
    commits: list[tuple[int, int]]  # (trace_id, t_commit_ns)
    commits_lost: bool = False


def _merge_ranges(ranges: list[tuple[int, int]]) -> list[tuple[int, int]]:
    if not ranges:
        return []
    rs = sorted(ranges)
    out = [list(rs[0])]
    for a, b in rs[1:]:
        if a <= out[-1][1]:
            if b > out[-1][1]:
                out[-1][1] = b
        else:
            out.append([a, b])
    return [(int(a), int(b)) for a, b in out]


class PointRing:
    """Bounded shared-memory point store. See module docs and docs/ring.md."""

    def __init__(self, max_points: int, channels: Sequence[ChannelSpec | str] = (), eviction: str = "drop_oldest",
                 importance_field: str | None = None, max_staleness_ms: float = 0.0,
                 classification_weights: dict[int, float] | None = None, name: str | None = None,
                 *, _attach_segment: Segment | None = None, _config: dict | None = None):
        self._tlock = threading.RLock()
        self._depth = 0
        self._otile: np.ndarray | None = None
        self._otile32: np.ndarray | None = None
        self._otile_origin: tuple | None = None
        self._bounds: tuple[int, float, float] = (-1, 0.0, 0.0)  # (origin gen, lowest, highest in-range value)
        self._closed = False
        if _attach_segment is not None:
            self._seg = _attach_segment
            cfg = _config
            self.layout = RingLayout.from_dict(cfg["layout"])
            self.eviction = cfg["eviction"]
            self.importance_field = cfg["importance_field"]
            self.max_staleness_ms = float(cfg["max_staleness_ms"])
            self.classification_weights = {int(k): float(v) for k, v in (cfg["classification_weights"] or {}).items()} or None
            self._map()
            self._finalizer = weakref.finalize(self, _finalize_segment, self._seg, False)
            return
        if isinstance(eviction, str) and eviction.lower() in _EVICTION_ALIASES:
            eviction = _EVICTION_ALIASES[eviction.lower()]
        else:
            raise RingConfigError(f"eviction must be one of {EVICTIONS} (or 'fifo'), got {eviction!r}")
        try:
            max_staleness_ms = float(max_staleness_ms or 0.0)
        except (TypeError, ValueError):
            raise RingConfigError(f"max_staleness_ms must be a number, got {max_staleness_ms!r}") from None
        if not np.isfinite(max_staleness_ms) or max_staleness_ms < 0:
            raise RingConfigError(f"max_staleness_ms must be >= 0, got {max_staleness_ms!r}")
        layout = RingLayout(max_points, as_channel_specs(channels))  # validates max_points
        self.layout = layout
        self.eviction = eviction
        self.importance_field = importance_field
        self.max_staleness_ms = max_staleness_ms
        self.classification_weights = ({int(k): float(v) for k, v in classification_weights.items()}
                                       if classification_weights else None)
        cfg = {"layout": layout.to_dict(), "eviction": eviction, "importance_field": importance_field,
               "max_staleness_ms": max_staleness_ms,
               "classification_weights": {str(k): v for k, v in (self.classification_weights or {}).items()}}
        blob = dumps_json(cfg)
        if len(blob) > CONFIG_MAX:
            raise RingConfigError("ring configuration too large for the header")
        self._seg = Segment(name or new_name("pfring"), HEADER_SIZE + data_size(layout), create=True)
        self._finalizer = weakref.finalize(self, _finalize_segment, self._seg, True)
        mm = self._seg.mm
        mm[16:20] = len(blob).to_bytes(4, "little")
        mm[24:32] = data_size(layout).to_bytes(8, "little")
        mm[CONFIG_OFF:CONFIG_OFF + len(blob)] = blob
        self._map()
        if self._imp_unit:
            self._imp[:] = 1.0
        for _, vals, _ in self._chans.values():  # never written = missing: drawn in render.color
            if vals.dtype.kind == "f":
                vals.fill(np.nan)
        st = self._st
        st[I_CAP] = layout.capacity
        st[I_EPOCH] = time.monotonic_ns()
        st[I_FINGERPRINT] = layout.fingerprint()
        st[I_OWNER_PID] = os.getpid()
        mm[8:12] = VERSION.to_bytes(4, "little")
        mm[12:16] = HEADER_SIZE.to_bytes(4, "little")
        mm[0:8] = MAGIC  # written last: a half-initialised segment never matches

    # ------------------------------------------------------------------ attach / lifecycle
    @classmethod
    def attach(cls, name: str, layout: RingLayout | None = None) -> "PointRing":
        """Attach to an existing ring by name (does not own it; ``close()`` only detaches)."""
        seg = Segment(name, create=False)
        try:
            mm = seg.mm
            if seg.size < HEADER_SIZE or bytes(mm[0:8]) != MAGIC:
                raise RingAttachError(f"segment {name!r} is not a pointflow ring (bad magic)")
            ver = int.from_bytes(mm[8:12], "little")
            if ver != VERSION:
                raise RingAttachError(f"ring {name!r} has version {ver}, this code reads version {VERSION}")
            if int.from_bytes(mm[12:16], "little") != HEADER_SIZE:
                raise RingAttachError(f"ring {name!r} has an unexpected header size")
            n = int.from_bytes(mm[16:20], "little")
            try:
                cfg = json.loads(bytes(mm[CONFIG_OFF:CONFIG_OFF + n]))
                lay = RingLayout.from_dict(cfg["layout"])
            except Exception as e:  # noqa: BLE001
                raise RingAttachError(f"ring {name!r} has an unreadable layout: {e}") from None
            st = np.ndarray((N_STATE,), np.int64, buffer=mm, offset=STATE_OFF)
            if int(st[I_FINGERPRINT]) != lay.fingerprint() or int(st[I_CAP]) != lay.capacity:
                raise RingAttachError(f"ring {name!r}: header does not match its layout")
            if seg.size != HEADER_SIZE + data_size(lay) or int.from_bytes(mm[24:32], "little") != data_size(lay):
                raise RingAttachError(f"ring {name!r}: segment size does not match its layout")
            if layout is not None and layout.fingerprint() != lay.fingerprint():
                raise RingAttachError(f"ring {name!r} has layout {lay.to_dict()}, expected {layout.to_dict()}")
            del st
        except BaseException:
            seg.close()
            raise
        return cls(lay.capacity, _attach_segment=seg, _config=cfg)

    def _map(self) -> None:
        mm = self._seg.mm
        # int64 state as a memoryview: Python-int indexing is several times cheaper than numpy scalars
        self._stmv = memoryview(mm)[STATE_OFF:STATE_OFF + 8 * N_STATE]
        self._st = self._stmv.cast("q")
        self._fst = np.ndarray((N_FSTATE,), np.float64, buffer=mm, offset=FSTATE_OFF)
        self._dirty = np.ndarray((DIRTY_MAX, 2), np.int64, buffer=mm, offset=DIRTY_OFF)
        self._commits = np.ndarray((COMMIT_N, 2), np.int64, buffer=mm, offset=COMMIT_OFF)
        # the same two tables as flat int64 memoryviews for the push path (cheaper element access)
        self._dmv = memoryview(mm)[DIRTY_OFF:DIRTY_OFF + 16 * DIRTY_MAX].cast("q")
        self._cmv = memoryview(mm)[COMMIT_OFF:COMMIT_OFF + 16 * COMMIT_N].cast("q")
        self.arrays = map_arrays(mm, HEADER_SIZE, self.layout)
        self._pos = self.arrays["positions"]
        self._t = self.arrays["t_ingest_ms"]
        self._imp = self.arrays["importance"]
        self._gen = self.arrays["generation"]
        self._pflat = self._pos.reshape(-1)  # flat float32 view of the offsets (x, y, z per slot)
        self._chans = {c.name: (c, self.arrays["ch:" + c.name], self.arrays["gen:" + c.name]) for c in self.layout.channels}
        self._all = list(self.arrays.values())
        self.capacity = self.layout.capacity
        #: No importance field and no class weights: every point's importance is 1.0, written
        #: once when the ring is created instead of with every push (4 B per point less).
        self._imp_unit = self.importance_field is None and not self.classification_weights

    @property
    def name(self) -> str:
        return self._seg.name

    @property
    def owner(self) -> bool:
        return self._seg.owner

    @property
    def channels(self) -> tuple[ChannelSpec, ...]:
        return self.layout.channels

    def close(self) -> None:
        """Detach; the owner also unlinks the segment (idempotent)."""
        if self._closed:
            return
        self._closed = True
        for a in ("arrays", "_pos", "_pflat", "_t", "_imp", "_gen", "_chans", "_all", "_fst", "_dirty", "_commits",
                  "_otile", "_otile32"):
            self.__dict__.pop(a, None)
        for a in ("_st", "_stmv", "_dmv", "_cmv"):
            mv = self.__dict__.pop(a, None)
            if mv is not None:
                mv.release()
        self._finalizer()

    def unlink(self) -> None:
        """Remove the segment name now (owner only); attached processes keep their mapping."""
        self._seg.unlink()

    def __enter__(self) -> "PointRing":
        return self

    def __reduce__(self):
        # pickling (e.g. as a multiprocessing argument) attaches by name in the receiving process
        return (PointRing.attach, (self.name,))

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"PointRing(name={self.name!r}, capacity={self.capacity}, eviction={self.eviction!r}, owner={self.owner})"

    # ------------------------------------------------------------------ locking
    @contextmanager
    def lock(self) -> Iterator[None]:
        """Exclusive cross-process lock (flock on the segment's fd; freed if the holder dies). Reentrant."""
        with self._tlock:
            if self._depth == 0:
                if self._closed:
                    raise RuntimeError("ring is closed")
                fcntl.flock(self._seg.fd, fcntl.LOCK_EX)
            self._depth += 1
            try:
                yield
            finally:
                self._depth -= 1
                if self._depth == 0:
                    fcntl.flock(self._seg.fd, fcntl.LOCK_UN)

    # ------------------------------------------------------------------ helpers
    def _now_ms(self) -> float:
        return (time.monotonic_ns() - int(self._st[I_EPOCH])) / 1e6

    def _origin(self) -> np.ndarray:
        return self._fst[0:3]

    def _mark(self, start: int, count: int) -> None:
        """Record slots [start, start+count) (mod capacity) as dirty."""
        st = self._st
        if st[I_DIRTY_FULL]:
            return
        cap = self.capacity
        if count >= cap:
            st[I_DIRTY_FULL] = 1
            return
        end = start + count
        if end <= cap:
            self._add_range(start, end)
        else:
            self._add_range(start, cap)
            self._add_range(0, end - cap)

    def _add_range(self, a: int, b: int) -> None:
        st = self._st
        n = st[I_DIRTY_N]
        d = self._dmv  # flat int64 view of the dirty table: d[2i], d[2i+1] = range i
        if n:
            i = 2 * n - 2
            la, lb = d[i], d[i + 1]
            if a <= lb and b >= la:
                if a < la:
                    d[i] = a
                if b > lb:
                    d[i + 1] = b
                return
        if n >= DIRTY_MAX:
            st[I_DIRTY_FULL] = 1
            return
        d[2 * n] = a
        d[2 * n + 1] = b
        st[I_DIRTY_N] = n + 1

    def _prepare(self, n: int, channels: dict) -> tuple[list, np.ndarray | None]:
        """Convert incoming channels (outside the lock). Returns [(spec, values, genarr, valarr)], importance."""
        prepared = []
        for name, (spec, vals, gens) in self._chans.items():
            arr = channels.get(name)
            if arr is None:
                continue
            arr = np.asarray(arr)
            if arr.shape[0] != n:
                raise ValueError(f"channel {name!r} has {arr.shape[0]} values for {n} points")
            if spec.width == 1:
                if arr.ndim == 2 and arr.shape[1] == 1:
                    arr = arr[:, 0]
                if arr.ndim != 1:
                    raise ValueError(f"channel {name!r} must have shape ({n},), got {arr.shape}")
            else:
                if arr.ndim != 2 or arr.shape[1] != spec.width:
                    raise ValueError(f"channel {name!r} must have shape ({n}, {spec.width}), got {arr.shape}")
            tdt = vals.dtype
            if tdt == np.uint8 and arr.dtype != np.uint8:
                if arr.dtype == np.uint16:
                    arr = (arr >> 8).astype(np.uint8)
                elif arr.dtype.kind == "f":
                    a = np.nan_to_num(arr, nan=0.0)
                    if a.size and float(np.max(a)) <= 1.0:
                        a = a * 255.0
                    arr = np.clip(np.rint(a), 0, 255).astype(np.uint8)
                else:
                    arr = np.clip(arr, 0, 255).astype(np.uint8)
            prepared.append((vals, gens, arr))
        imp = None
        if self.importance_field is not None and self.importance_field in channels:
            imp = channels[self.importance_field]
            if type(imp) is not np.ndarray or imp.dtype != np.float32 or imp.shape != (n,):
                imp = np.asarray(imp, dtype=np.float32).reshape(n)
        if self.classification_weights and "classification" in channels:
            cls = np.asarray(channels["classification"]).reshape(n)
            imp = np.ones(n, np.float32) if imp is None else imp.copy()
            for k, w in self.classification_weights.items():
                imp[cls == k] = w
        if imp is not None and n and not self._imp_ok(imp):
            imp = np.where(np.isfinite(imp) & (imp > 0), imp, 0.0).astype(np.float32)
        return prepared, imp

    @staticmethod
    def _imp_ok(imp: np.ndarray) -> bool:
        """True iff every importance is >= 0 and finite (float32 (n,), n >= 1)."""
        # one integer reduction: as uint32, +0.0 .. the largest finite float32 are exactly the bit
        # patterns below 0x7F800000 (+inf); negatives (sign bit), NaN and inf lie above. -0.0 also
        # lies above, so a miss falls back to the float test, which accepts -0.0.
        if int(imp.view(np.uint32).max()) < 0x7F800000:
            return True
        return bool(imp.min() >= 0 and imp.max() < np.inf)

    def _write(self, slot: int, pos: np.ndarray, a: int, b: int, t_ms: float, g: int, prepared, imp,
               xf=None) -> None:
        """Write incoming points [a, b) to slots slot.. (mod capacity); b - a <= capacity.
        ``xf``: a transform that places the points as they are written (see push)."""
        cap = self.capacity
        n = b - a
        pflat = pos.reshape(-1)
        if xf is None:
            otile = self._origin_tile(n, pflat.dtype.char == "f")
        else:
            origin = self._fst[0:3].copy()
        dflat = self._pflat
        if slot + n <= cap:
            segs = ((slot, slot + n, a, b),)  # the common case: no wrap, one numpy call per array
        else:
            segs = ((slot, cap, a, a + cap - slot), (0, slot + n - cap, a + cap - slot, b))
        for s0, s1, c0, c1 in segs:
            # offsets computed in float64, stored as float32 (flat: avoids numpy's slow 3-wide broadcast)
            if xf is None:
                np.subtract(pflat[3 * c0:3 * c1], otile[:3 * (c1 - c0)], out=dflat[3 * s0:3 * s1], casting="unsafe")
            else:
                xf.apply(pos[c0:c1], origin, dflat[3 * s0:3 * s1])
            self._t[s0:s1] = t_ms
            self._gen[s0:s1] = g
            if imp is None:
                if not self._imp_unit:
                    self._imp[s0:s1] = 1.0
            else:
                self._imp[s0:s1] = imp[c0:c1]
            for vals, gens, arr in prepared:
                vals[s0:s1] = arr[c0:c1]
                gens[s0:s1] = g

    def _origin_tile(self, n: int, f32: bool = False) -> np.ndarray:
        """The origin repeated n times (flat), cached until the origin changes: float64, or for
        float32 positions float32 when the origin is exactly a float32 value.

        float32 positions minus a float32 origin in float32 arithmetic give bit for bit the
        float64 difference rounded once to float32: the difference of two 24-bit floats rounded
        to 53 bits and then to 24 is the same as rounded to 24 directly (double rounding is
        innocuous when 53 >= 2 * 24 + 1, Figueroa 1995; a difference that underflows is exact in
        both). That path is a plain float32 subtraction instead of a float64 one through a
        casting buffer, about 2.5x faster (tests/ring/test_fastpath.py compares both)."""
        key = self._st[I_ORIGIN_GEN]
        ot = self._otile
        if ot is None or self._otile_origin != key or ot.shape[0] < 3 * n:
            o = self._fst[0:3].copy()
            ot = np.tile(o, max(n, 1024))
            o32 = o.astype(np.float32)
            self._otile32 = np.tile(o32, max(n, 1024)) if np.array_equal(o32.astype(np.float64), o) else None
            self._otile, self._otile_origin = ot, key
        if f32 and self._otile32 is not None:
            return self._otile32
        return ot

    def _window(self, arr: np.ndarray, head: int, W: int) -> np.ndarray:
        """arr at the W oldest logical positions."""
        if head + W <= self.capacity:
            return arr[head:head + W]
        return np.concatenate((arr[head:], arr[:head + W - self.capacity]))

    def _scores(self, head: int, W: int, now_ms: float) -> np.ndarray:
        """Scores of the W oldest points (logical order): importance x 0.5^(age / max_staleness_ms)."""
        imp = self._window(self._imp, head, W)
        t = self._window(self._t, head, W)
        h = self.max_staleness_ms
        if h > 0:
            # ranked in the log domain: log2(score) = log2(importance) - age / h. Same order as the
            # score, but every step is monotone under float rounding, so uniform importance stays FIFO.
            x = np.empty(W, np.float32)
            np.subtract(t, now_ms, out=x, casting="unsafe")
            x *= np.float32(1.0 / h)
            if imp.min() > 0:
                x += np.log2(imp)
            else:  # importance 0 -> log2 = -inf: always evicted first
                with np.errstate(divide="ignore"):
                    x += np.log2(imp)
            return x
        return imp.copy()

    @staticmethod
    def _evict_mask(score: np.ndarray, p: int) -> np.ndarray:
        """Keep-mask over the window: evicts the p lowest scores, the oldest first among equal scores."""
        W = score.shape[0]
        S = W - p  # survivors
        if W >= 8192 and S + 1 <= W // 8:
            # lower bound for the (S+1)-th largest: the minimum of S+1 block maxima
            starts = (np.arange(S + 1) * W) // (S + 1)
            lb = np.maximum.reduceat(score, starts).min()
            cand = score[score >= lb]
            v = np.partition(cand, cand.shape[0] - S - 1)[cand.shape[0] - S - 1]
        else:
            v = np.partition(score, p - 1)[p - 1]  # the p-th smallest = largest evicted score
        keep = score > v
        need_keep = S - int(np.count_nonzero(keep))
        if need_keep:
            eq = np.flatnonzero(score == v)
            keep[eq[eq.shape[0] - need_keep:]] = True  # the newest among ties survive
        return keep

    # ------------------------------------------------------------------ push
    def push(self, positions, *, trace_id: "int | Sequence[int]" = 0,
             value_range: "tuple[float, float] | None" = None, transform=None, **channels) -> PushResult:
        """Store points (world coordinates, (N,3) float64/float32) with optional channels.

        ``trace_id`` may be a sequence when one push carries several coalesced chunks; each
        id goes into the commit log, so the cadence sees every chunk become visible.
        ``value_range`` is (min, max) over every coordinate when the caller already has it
        (ingest computes it to find non-finite points); it saves the ring those two passes and
        must hold every coordinate, or an out-of-range point could be stored.

        ``transform``: the positions are not yet in the ring's frame; the object places them
        as they are written (:class:`pointflow.frames.kernels.RigidTransform`: ``apply(pos,
        origin, out)`` writes the offsets of the placed ``pos`` from ``origin`` into the flat
        float32 ``out``, ``world(pos)`` returns the placed positions in float64). Then
        ``value_range`` bounds the placed coordinates; without it, or when a point may be out
        of range, or to choose the origin, the ring places the points first and goes on as
        without a transform."""
        pos = np.asarray(positions)
        dt = pos.dtype
        if dt is not _F64 and dt is not _F32 and dt != _F64 and dt != _F32:
            pos = pos.astype(np.float64)
        if not pos.flags.c_contiguous:
            pos = np.ascontiguousarray(pos)
        if pos.ndim == 1 and pos.shape[0] == 3:
            pos = pos.reshape(1, 3)
        if pos.ndim != 2 or pos.shape[1] != 3:
            raise ValueError(f"positions must have shape (N, 3), got {pos.shape}")
        n = pos.shape[0]
        if n == 0:
            return PushResult(0, 0)
        prepared, imp = self._prepare(n, channels)
        if transform is not None and (value_range is None or self.eviction not in ("drop_oldest", "drop_newest")):
            pos, transform = transform.world(pos), None
        # the range of all coordinates (NaN when any is NaN): when it lies within MAX_OFFSET of
        # every origin axis, no point needs the exact per-axis test (two passes; the only cost
        # the range rule adds to an ordinary push)
        if value_range is None:
            pflat = pos.reshape(-1)
            lo, hi = _min(pflat), _max(pflat)
        else:
            lo, hi = value_range
        rejected = 0
        # the lock, inlined (this is the hot path): thread lock + flock on the segment fd
        with self._tlock:
            if self._depth == 0:
                if self._closed:
                    raise RuntimeError("ring is closed")
                fcntl.flock(self._seg.fd, fcntl.LOCK_EX)
            self._depth += 1
            try:
                st = self._st
                if not st[I_ORIGIN_SET]:
                    if transform is not None:
                        pos, transform = transform.world(pos), None
                    self._choose_origin(pos)
                gen, blo, bhi = self._bounds
                if gen != st[I_ORIGIN_GEN] or not st[I_ORIGIN_SET]:
                    gen, blo, bhi = self._origin_bounds()
                if not (lo > blo and hi < bhi):  # some point may be out of range: the exact test
                    if transform is not None:
                        pos, transform = transform.world(pos), None
                    pos, prepared, imp, rejected = self._drop_out_of_range(pos, prepared, imp)
                    st[I_REJECTED] += rejected
                if pos.shape[0]:
                    written, dropped = self._push_locked(pos, pos.shape[0], trace_id, prepared, imp, transform)
                else:
                    written, dropped = 0, 0
            finally:
                self._depth -= 1
                if self._depth == 0:
                    fcntl.flock(self._seg.fd, fcntl.LOCK_UN)
        return PushResult(written, dropped, rejected)

    def _choose_origin(self, pos: np.ndarray) -> None:
        """Origin from the first push that has usable points: the per-axis (lower) median of its
        finite points with |coordinate| <= MAX_ORIGIN_ABS, rounded to whole units. Fewer than
        half the points, however absurd, cannot move it off the others."""
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(pos).all(axis=1) & (np.abs(pos) <= MAX_ORIGIN_ABS).all(axis=1)
        cand = pos[ok]
        m = cand.shape[0]
        if m == 0:
            return  # nothing usable: every point is rejected and the origin stays unset
        k = (m - 1) // 2
        med = np.partition(cand.astype(np.float64), k, axis=0)[k]
        self._fst[0:3] = np.round(med)
        st = self._st
        st[I_ORIGIN_SET] = 1
        st[I_ORIGIN_GEN] = st[I_GEN] + 1

    def _origin_bounds(self) -> tuple[int, float, float]:
        """(origin gen, lo, hi): every coordinate in (lo, hi) is within MAX_OFFSET of the origin
        on any axis (a conservative box around all three axes; the exact test is per axis)."""
        st = self._st
        if not st[I_ORIGIN_SET]:
            return (-1, np.inf, -np.inf)  # nothing passes: the exact test rejects all
        o = self._fst[0:3]
        b = (int(st[I_ORIGIN_GEN]), float(o.max()) - MAX_OFFSET, float(o.min()) + MAX_OFFSET)
        self._bounds = b
        return b

    def _drop_out_of_range(self, pos, prepared, imp):
        """Keep the points whose offset from the origin is below MAX_OFFSET on every axis (not
        NaN, not inf); the channels and importance follow. Returns (pos, prepared, imp, rejected)."""
        n = pos.shape[0]
        if not self._st[I_ORIGIN_SET]:
            keep = np.zeros(n, bool)
        else:
            with np.errstate(invalid="ignore", over="ignore"):
                keep = (np.abs(pos.astype(np.float64) - self._fst[0:3]) < MAX_OFFSET).all(axis=1)
        k = int(np.count_nonzero(keep))
        if k == n:
            return pos, prepared, imp, 0
        pos = np.ascontiguousarray(pos[keep])
        prepared = [(vals, gens, arr[keep]) for vals, gens, arr in prepared]
        if imp is not None:
            imp = imp[keep]
        return pos, prepared, imp, n - k

    def _push_locked(self, pos, n, trace_id, prepared, imp, xf=None) -> tuple[int, int]:
        cap = self.capacity
        st = self._st
        g = int(st[I_GEN]) + 1
        if not g & GEN_MASK:  # a slot's stamp is the low 32 bits; 0 is a slot never written
            g += 1
        st[I_GEN] = g
        g &= GEN_MASK
        now_ns = time.monotonic_ns()
        t_ms = (now_ns - int(st[I_EPOCH])) / 1e6
        head, size = int(st[I_HEAD]), int(st[I_SIZE])
        free = cap - size
        tail = (head + size) % cap
        ev = self.eviction
        if ev == "drop_newest":
            acc = min(n, free)
            if acc:
                self._write(tail, pos, 0, acc, t_ms, g, prepared, imp, xf)
                self._mark(tail, acc)
                st[I_SIZE] = size + acc
            written, dropped = acc, n - acc
        elif ev == "drop_oldest" or n <= free:
            if n >= cap:
                a = n - cap
                self._write(tail, pos, a, n, t_ms, g, prepared, imp, xf)
                st[I_HEAD] = tail
                st[I_SIZE] = cap
                st[I_DIRTY_FULL] = 1
                written, dropped = cap, size + a
            else:
                self._write(tail, pos, 0, n, t_ms, g, prepared, imp, xf)
                self._mark(tail, n)
                over = n - free if n > free else 0
                st[I_HEAD] = (head + over) % cap
                st[I_SIZE] = size + n - over
                written, dropped = n, over
        else:
            written, dropped = self._push_importance(pos, n, t_ms, g, prepared, imp)
        st[I_DROPPED] += dropped
        st[I_WRITES] += 1
        st[I_TOTAL_WRITTEN] += written
        st[I_LAST_PUSH_NS] = now_ns
        tids = (trace_id,) if isinstance(trace_id, _INTS) else trace_id
        t_commit = time.monotonic_ns()
        cm = self._cmv  # flat int64 view of the commit log: cm[2i], cm[2i+1] = entry i
        for tid in tids:  # one entry per chunk of a coalesced push (a handful, not per point)
            if tid:
                c = st[I_COMMIT_COUNT]
                v = int(tid) & 0xFFFFFFFFFFFFFFFF  # stored as the int64 with the same bits
                i = 2 * (c % COMMIT_N)
                cm[i] = v - (1 << 64) if v >= 1 << 63 else v
                cm[i + 1] = t_commit
                st[I_COMMIT_COUNT] = c + 1
        return int(written), int(dropped)

    def _push_importance(self, pos, n, t_ms, g, prepared, imp) -> tuple[int, int]:
        st = self._st
        cap = self.capacity
        K = K_CANDIDATES
        head, size = int(st[I_HEAD]), int(st[I_SIZE])
        a = 0
        free = cap - size
        if free:  # fill the free slots first (no eviction)
            tail = (head + size) % cap
            self._write(tail, pos, 0, free, t_ms, g, prepared, imp)
            self._mark(tail, free)
            size = cap
            st[I_SIZE] = cap
            a = free
        pmax = max(1, cap - K + 1, (cap + 1) // 2)
        own = a  # points of this chunk currently in the ring
        dropped = 0
        while a < n:
            p = min(n - a, pmax)
            W = min(cap, p + K - 1)
            score = self._scores(head, W, t_ms)
            if p == 1:
                # exact sequential rule: first strict minimum among the K oldest, swap with head
                m = int(np.argmin(score))
                if m:
                    s = (head + m) % cap
                    idx = [head, s]
                    rev = [s, head]
                    for arr in self._all:
                        arr[idx] = arr[rev]
                if own and int(self._gen[head]) == g:
                    own -= 1
            elif p < W:
                # batched rule: evict the p lowest scores among the oldest W (oldest first on ties),
                # survivors keep their relative order and move to logical positions p..W-1
                keep = self._evict_mask(score, p)
                if own:
                    own -= int(np.count_nonzero(~keep & (self._window(self._gen, head, W) == g)))
                if keep[:p].any():
                    surv = np.flatnonzero(keep)
                    tgt = np.arange(p, W)
                    mv = surv != tgt
                    src = surv[mv] + head
                    dst = tgt[mv] + head
                    if head + W > cap:
                        src %= cap
                        dst %= cap
                    for arr in self._all:
                        arr[dst] = arr[src]
            elif own:
                own -= int(np.count_nonzero(self._window(self._gen, head, W) == g))
            self._write(head, pos, a, a + p, t_ms, g, prepared, imp)
            self._mark(head, W)
            head = (head + p) % cap
            dropped += p
            a += p
            own += p
        st[I_HEAD] = head
        return own, dropped

    def push_chunk(self, chunk) -> PushResult:
        """Push a :class:`pointflow.chunk.PointChunk`."""
        return self.push(chunk.positions, trace_id=int(getattr(chunk, "trace_id", 0) or 0), **chunk.channels)

    # ------------------------------------------------------------------ reading
    def stats(self, wait: bool = True) -> RingStats:
        """The ring's counters. ``wait=False`` reads them without the lock, so it never waits
        for a process that holds it (frozen, starved, or stuck in a call): each counter is
        one aligned 8-byte word, read whole, though two counters may come from either side
        of a push in progress. The supervisor reads this way: supervision must not stop
        because a stage stopped inside a push (docs/reliability.md). Once no process
        writes (every writer has exited), the values are exact either way."""
        if not wait:
            return self._read_stats()
        with self.lock():
            return self._read_stats()

    @property
    def total_written(self) -> int:
        """Points stored since the ring was made (or reset), read without the lock (one
        aligned 8-byte word). Exact for the ring's only writer between its pushes, and for
        anyone once no process writes."""
        return int(self._st[I_TOTAL_WRITTEN])

    def _read_stats(self) -> RingStats:
        st = self._st
        size = int(st[I_SIZE])
        origin = tuple(float(x) for x in self._fst[0:3]) if st[I_ORIGIN_SET] else None
        return RingStats(total_points=size, dropped_points=int(st[I_DROPPED]), under_pressure=size >= self.capacity,
                         capacity=self.capacity, head=int(st[I_HEAD]), origin=origin, epoch_ns=int(st[I_EPOCH]),
                         write_count=int(st[I_WRITES]), eviction=self.eviction,
                         total_written=int(st[I_TOTAL_WRITTEN]), resets=int(st[I_RESETS]),
                         rejected_points=int(st[I_REJECTED]))

    def _logical_slots(self) -> np.ndarray:
        head, size = int(self._st[I_HEAD]), int(self._st[I_SIZE])
        s = np.arange(head, head + size)
        if head + size > self.capacity:
            s %= self.capacity
        return s

    def snapshot(self) -> Snapshot:
        """A consistent copy of the ring in logical order (oldest first)."""
        with self.lock():
            slots = self._logical_slots()
            off = self._pos[slots]
            t = self._t[slots]
            imp = self._imp[slots]
            gen = self._gen[slots]
            raw = {name: (vals[slots], gens[slots]) for name, (_, vals, gens) in self._chans.items()}
            origin = self._fst[0:3].copy() if self._st[I_ORIGIN_SET] else None
            epoch = int(self._st[I_EPOCH])
        pos = off.astype(np.float64)
        if origin is not None:
            pos += origin
        chans, present = {}, {}
        for name, (v, gg) in raw.items():
            ok = gg == gen
            if v.dtype.kind == "f":
                v = np.where(ok.reshape((-1,) + (1,) * (v.ndim - 1)), v, np.nan).astype(v.dtype)
            chans[name] = v
            present[name] = ok
        return Snapshot(pos, chans, present, t, imp, slots.astype(np.int64), gen,
                        tuple(float(x) for x in origin) if origin is not None else None, epoch)

    def get_point(self, slot: int) -> PointRecord | None:
        """The current occupant of ``slot`` (world position, present channels, ingest time) or None."""
        slot = int(slot)
        if not 0 <= slot < self.capacity:
            return None
        with self.lock():
            head, size = int(self._st[I_HEAD]), int(self._st[I_SIZE])
            if (slot - head) % self.capacity >= size:
                return None
            g = int(self._gen[slot])
            pos = self._pos[slot].astype(np.float64) + self._fst[0:3]
            ch = {}
            for name, (spec, vals, gens) in self._chans.items():
                if int(gens[slot]) == g:
                    v = vals[slot]
                    ch[name] = v.copy() if spec.width > 1 else v.item()
            return PointRecord(slot, pos, ch, float(self._t[slot]), g, float(self._imp[slot]))

    def temporal_stats(self, window_ms: float) -> TemporalStats:
        """Oldest/newest point age and the number of points with age <= window_ms (inclusive)."""
        with self.lock():
            head, size = int(self._st[I_HEAD]), int(self._st[I_SIZE])
            now = self._now_ms()
            if size == 0:
                return TemporalStats(None, None, 0)
            if size == self.capacity:
                t = self._t
            elif head + size <= self.capacity:
                t = self._t[head:head + size]
            else:
                t = self._t[self._logical_slots()]
            tmin, tmax = float(t.min()), float(t.max())
            cnt = int(np.count_nonzero(t >= now - float(window_ms)))
        return TemporalStats(max(0.0, now - tmin), max(0.0, now - tmax), cnt)

    def reset(self) -> None:
        """Clear points and counters (the generation counter and epoch continue); next handoff is full."""
        with self.lock():
            st = self._st
            st[I_HEAD] = 0
            st[I_SIZE] = 0
            st[I_DROPPED] = 0
            st[I_REJECTED] = 0
            st[I_WRITES] = 0
            st[I_TOTAL_WRITTEN] = 0
            st[I_ORIGIN_SET] = 0
            st[I_DIRTY_N] = 0
            st[I_DIRTY_FULL] = 1
            st[I_RESETS] += 1
            self._fst[0:3] = 0.0

    # ------------------------------------------------------------------ cadence side
    def take_changes(self) -> Changes:
        """Dirty ranges and commits since the previous call (single consumer: the cadence). Caller should hold lock()."""
        with self.lock():
            st = self._st
            if st[I_DIRTY_FULL]:
                dirty = None
            else:
                n = int(st[I_DIRTY_N])
                dirty = _merge_ranges([(int(a), int(b)) for a, b in self._dirty[:n]])
                if dirty and dirty[0] == (0, self.capacity):
                    dirty = None
            st[I_DIRTY_N] = 0
            st[I_DIRTY_FULL] = 0
            c, taken = int(st[I_COMMIT_COUNT]), int(st[I_COMMIT_TAKEN])
            lost = c - taken > COMMIT_N
            taken = max(taken, c - COMMIT_N)
            commits = []
            if c > taken:
                idx = np.arange(taken, c) % COMMIT_N
                rows = self._commits[idx]
                commits = [(int(np.int64(r[0]).view(np.uint64)), int(r[1])) for r in rows]
            st[I_COMMIT_TAKEN] = c
            return Changes(dirty, commits, lost)

    def header_state(self) -> dict:
        """head, size, origin (float64 array copy), epoch_ns, write_count. Caller should hold lock()."""
        st = self._st
        return {"head": int(st[I_HEAD]), "size": int(st[I_SIZE]), "origin": self._fst[0:3].copy(),
                "origin_set": bool(st[I_ORIGIN_SET]), "epoch_ns": int(st[I_EPOCH]), "write_count": int(st[I_WRITES])}
