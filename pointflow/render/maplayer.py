"""The map layer of the render stage: the map stage's points as extra slots after the ring's.

Every tier draws a :class:`~pointflow.render.base.FrameInput`; with a ``map:`` block the
render stage hands it one whose slots are the ring's ``R`` slots followed by
``map.point_budget`` map slots, so depth, colour, eye-dome lighting and picking treat map
and live points by the same rules and no tier changes. The combined frame is a render-private
copy kept current range by range: the ring's dirty ranges (and slots that became free or
occupied) are copied from the slab, unoccupied ring slots and empty map slots hold NaN
positions (every tier skips non-finite positions; they are not counted as ``nonfinite``),
and the map slots change only when a map version message arrives
(:mod:`pointflow.render.mapregion`). World positions are converted to float32 offsets from the
frame's origin in float64, so a georeferenced map and live points share one origin (the
ring's; the map's own while the ring is empty). Map points carry ingest time +inf (a time
window never hides them) and importance +inf (importance sampling keeps them: the map is
thinned by its level of detail already). The combined frame is ``head = 0``, ``size =
capacity``: logical order is slot order.
"""
from __future__ import annotations

import time
from typing import Optional

import numpy as np
import zmq

from . import mapregion as mr
from .base import FrameInput, merge_ranges


#: The map stage hears of a moving camera at most this often.
CAMERA_PERIOD_S = 0.1

#: A camera looking further than this from the ring's origin, and nearer the map's, has the
#: frame drawn from the map's origin (float32 steps are 1 mm at 10 km).
FAR_FROM_ORIGIN = 10_000.0


class MapLayer:
    """Receives map versions, composes the combined frame, publishes the cameras, names
    picked map points. Everything here runs between frames and copies only what changed."""

    def __init__(self, cfg, ctx, ring_capacity: int):
        self.ring_cap = int(ring_capacity)
        self.slots = int(cfg.map.point_budget)
        self.capacity = self.ring_cap + self.slots
        self.log = ctx.log
        self.source_names = [s.name for s in cfg.sources]
        self.pull = ctx.zmq.socket(zmq.PULL)
        self.pull.setsockopt(zmq.LINGER, 0)
        self.pull.bind(ctx.endpoints.map)
        self.push = ctx.zmq.socket(zmq.PUSH)
        self.push.setsockopt(zmq.LINGER, 0)
        self.push.setsockopt(zmq.SNDHWM, 64)
        self.push.connect(ctx.endpoints.map_camera)
        self.region: Optional[mr.MapRegion] = None
        self.files: list[str] = []
        self.map_origin: Optional[np.ndarray] = None
        self.map_box: Optional[tuple] = None  # the map's (lo, hi), world float64, once the map stage knows it
        self.units: Optional[dict] = None  # {"xy", "z"} from the map's CRS (map/source.py header_units), or None
        self.preview = False  # the version held is a preview (the map's index is still being built)
        self.warned_apart = False  # the render stage said once that map and live points lie apart
        self.previews = 0
        self.occupied = np.zeros(self.slots, bool)  # map slots holding a point
        self.map_ranges: dict[str, tuple[float, float]] = {}
        self.version = -1
        self.points = 0
        self.nodes = 0
        self.pending: Optional[list] = []  # map-slot ranges changed since the last frame (None = all)
        self.arrays: Optional[dict] = None
        self.origin: Optional[np.ndarray] = None  # the origin the map slots were converted for
        self._ring_occ: Optional[tuple[int, int]] = None  # (head, size) of the ring last composed
        self._ring_origin: Optional[np.ndarray] = None  # the ring's origin last composed
        self.focus: Optional[np.ndarray] = None  # where the last drawn camera looked
        self.padding_draws = 0  # NaN slots of the combined frames drawn (not counted "nonfinite")
        self._padding = 0
        self.versions = 0
        self.bad_messages = 0
        self.t_version_ns = 0
        self._last_cams = None
        self._t_cams = 0.0
        self._undrawn: Optional[list] = []  # dirty ranges of a composed frame not drawn (None = all)
        self.hello()

    # ------------------------------------------------------------------ map stage -> render
    def hello(self) -> None:
        self._send({"type": "hello"})

    def _send(self, msg: dict) -> None:
        try:
            self.push.send(mr.encode(msg), zmq.NOBLOCK)
        except zmq.Again:  # the map stage is gone or behind: it asks again / we say hello again
            pass

    def poll(self) -> bool:
        """Apply every version message waiting (copies into the map slots); True if any."""
        got = False
        while self.pull.poll(0, zmq.POLLIN):
            msg = mr.decode(self.pull.recv())
            if msg is not None and msg.get("type") == "bounds":  # known before the map is open (its header)
                self._bounds(msg)
                continue
            if msg is None or msg.get("type") != "version":
                self.bad_messages += 1
                continue
            try:
                self._apply(msg)
            except (OSError, ValueError, KeyError, TypeError) as exc:
                self.bad_messages += 1
                self.log.warning("map version %s not taken: %s", msg.get("version"), exc)
                continue
            self._send({"type": "ack", "version": int(msg["version"])})
            got = True
        return got

    def _bounds(self, msg: dict) -> None:
        if msg.get("type") == "bounds" and msg.get("bounds") is None:  # the map could not be opened
            self.map_box = self.units = None
            return
        if "units" in msg:
            self.units = _units(msg["units"])
        try:
            lo, hi = (np.asarray(b, np.float64).reshape(3) for b in msg["bounds"])
        except (KeyError, TypeError, ValueError):
            self.bad_messages += 1
            return
        if np.isfinite(lo).all() and np.isfinite(hi).all() and (hi >= lo).all():
            self.map_box = (lo, hi)

    def _apply(self, msg: dict) -> None:
        if msg.get("bounds") is not None:
            self._bounds(msg)
        chans = [tuple(c) for c in msg["channels"]]
        if self.region is None or self.region.path != msg["region"] or self.region.channels != chans:
            if self.region is not None:
                self.region.close()
            self._last_cams = None  # a (new) map stage: tell it where the views look again
            self.region = mr.MapRegion.attach(msg["region"], int(msg["slots"]), chans)
            if self.region.slots != self.slots:
                raise ValueError(f"map region has {self.region.slots} slots, expected {self.slots}")
        self.files = list(msg.get("files") or [])
        self.map_origin = np.asarray(msg["origin"], np.float64)
        if self.arrays is not None:
            cleared = msg.get("cleared") or []
            if msg.get("full"):
                cleared = [(0, self.slots)]
            for a, b in cleared:
                self.occupied[a:b] = False
                self.arrays["positions"][self.ring_cap + a:self.ring_cap + b] = np.nan
            for a, b in msg.get("set") or []:
                self.occupied[a:b] = True
                self._copy_map(a, b)
            if self.pending is not None:
                self.pending.extend(cleared)
                self.pending.extend(tuple(r) for r in msg.get("set") or [])
        else:  # no frame yet: the first compose copies everything
            if msg.get("full"):
                self.occupied[:] = False
            for a, b in msg.get("cleared") or []:
                self.occupied[a:b] = False
            for a, b in msg.get("set") or []:
                self.occupied[a:b] = True
            self.pending = None
        self.map_ranges = {k: (float(v[0]), float(v[1])) for k, v in (msg.get("channel_ranges") or {}).items()}
        self.version = int(msg["version"])
        self.preview = bool(msg.get("preview"))
        self.previews += int(self.preview)
        self.points = int(msg.get("points", int(self.occupied.sum())))
        self.nodes = int(msg.get("nodes", 0))
        self.versions += 1
        self.t_version_ns = time.monotonic_ns()

    def _copy_map(self, a: int, b: int) -> None:
        """Map slots [a, b) from the region into the combined arrays (float64 -> offsets)."""
        A = self.arrays
        r = self.region
        o = self.origin if self.origin is not None else self.map_origin
        lo, hi = self.ring_cap + a, self.ring_cap + b
        occ = self.occupied[a:b]
        pos = (r.positions[a:b] - o).astype(np.float32)
        pos[~occ] = np.nan
        A["positions"][lo:hi] = pos
        for name, arr in A["channels"].items():
            src = r.channel.get(name)
            if src is None:
                arr[lo:hi] = 0 if arr.dtype.kind == "u" else np.nan
            else:
                arr[lo:hi] = src[a:b]

    # ------------------------------------------------------------------ the combined frame
    def _alloc(self, frame: FrameInput) -> None:
        C, R = self.capacity, self.ring_cap
        pos = np.full((C, 3), np.nan, np.float32)
        imp = np.empty(C, frame.importance.dtype)
        imp[R:] = np.inf
        t = np.empty(C, frame.t_ingest_ms.dtype)
        t[R:] = np.inf
        chans = {}
        for k, v in frame.channels.items():
            a = np.empty((C,) + v.shape[1:], v.dtype)
            a[R:] = 0 if v.dtype.kind == "u" else np.nan
            chans[k] = a
        self.arrays = {"positions": pos, "importance": imp, "t_ingest_ms": t, "channels": chans}

    def _ring_refresh(self, frame: FrameInput) -> Optional[list]:
        """Ring slot ranges to copy from the slab this frame (None = all): the dirty ranges
        and the slots that became free or occupied (eviction by age writes nothing)."""
        occ = (int(frame.head), int(frame.size))
        if frame.dirty is None or self._ring_occ is None:
            self._ring_occ = occ
            return None
        ranges = list(frame.dirty)
        if occ != self._ring_occ:
            ranges += xor_ranges(occupied_ranges(*self._ring_occ, self.ring_cap),
                                 occupied_ranges(*occ, self.ring_cap))
            self._ring_occ = occ
        return merge_ranges(ranges, self.ring_cap)

    def compose(self, frame: FrameInput) -> FrameInput:
        """The frame the tier draws: ``frame`` (the ring's, from the slab) plus the map slots."""
        self.poll()
        if self.arrays is None:
            self._alloc(frame)
            self.pending = None
        A, R = self.arrays, self.ring_cap
        origin = self._origin(frame)
        ring_origin = np.asarray(frame.origin, np.float64)
        if self.origin is None or not np.array_equal(origin, self.origin):
            self.origin = origin.copy()
            self.pending = None  # every map slot again, relative to the new origin
            self._ring_occ = None  # and every ring slot
        if self._ring_origin is None or not np.array_equal(ring_origin, self._ring_origin):
            self._ring_origin = ring_origin.copy()
            self._ring_occ = None
        shift = ring_origin - self.origin
        ring = self._ring_refresh(frame)
        for a, b in ([(0, R)] if ring is None else ring):
            if shift.any():  # the ring's offsets, moved to the frame's origin in float64
                A["positions"][a:b] = (frame.positions[a:b].astype(np.float64) + shift).astype(np.float32)
            else:
                A["positions"][a:b] = frame.positions[a:b]
            A["importance"][a:b] = frame.importance[a:b]
            A["t_ingest_ms"][a:b] = frame.t_ingest_ms[a:b]
            for k, arr in A["channels"].items():
                arr[a:b] = frame.channels[k][a:b]
            self._blank_free(frame, a, b)
        if self.pending is None:
            if self.region is not None:
                self._copy_map(0, self.slots)
            map_dirty = None
        else:
            map_dirty = [(R + a, R + b) for a, b in merge_ranges(self.pending, self.slots)]
        self.pending = []
        if ring is None or map_dirty is None or self._undrawn is None:
            dirty = None
        else:  # with what a frame composed but not drawn had changed (the tier never got it)
            dirty = merge_ranges(ring + map_dirty + self._undrawn, self.capacity)
        self._undrawn = None if dirty is None else list(dirty)
        ranges = dict(frame.channel_ranges)
        for k, (lo, hi) in self.map_ranges.items():
            if k in ranges and frame.size:
                ranges[k] = (min(ranges[k][0], lo), max(ranges[k][1], hi))
            elif k in A["channels"]:
                ranges[k] = (lo, hi)
        budget = None if frame.budget is None else int(frame.budget) + self.points
        self._padding = self.capacity - int(frame.size) - self.points
        return FrameInput(positions=A["positions"], importance=A["importance"], t_ingest_ms=A["t_ingest_ms"],
                          channels=A["channels"], head=0, size=self.capacity, capacity=self.capacity,
                          origin=self.origin, now_ms=frame.now_ms, channel_ranges=ranges, dirty=dirty,
                          budget=budget, seq=frame.seq, frame_seed=frame.frame_seed, live_slots=R,
                          map_box=self.map_box)

    def _origin(self, frame: FrameInput) -> np.ndarray:
        """The frame's one float64 origin: the ring's, or the map's while the ring is empty or
        while the camera looks nearer the map's origin than the ring's (a georeferenced map far
        from the live points would otherwise be float32 offsets of millions of metres)."""
        ring = np.asarray(frame.origin, np.float64)
        if self.map_origin is None:
            return ring
        if frame.size <= 0:
            return self.map_origin
        if self.focus is not None:
            to_ring = float(np.linalg.norm(self.focus - ring))
            # only where float32 offsets from the ring's origin would lose millimetres: a sensor
            # placed in the map never switches (a switch converts every slot again)
            if to_ring > FAR_FROM_ORIGIN and float(np.linalg.norm(self.focus - self.map_origin)) < to_ring:
                return self.map_origin
        return ring

    def _blank_free(self, frame: FrameInput, a: int, b: int) -> None:
        """NaN positions for the ring slots in [a, b) that hold no point."""
        R, h, s = self.ring_cap, int(frame.head), int(frame.size)
        if s >= R:
            return
        idx = np.arange(a, b)
        free = ((idx - h) % R) >= s
        if free.any():
            self.arrays["positions"][a:b][free] = np.nan

    def drawn(self, camera=None) -> None:
        """The composed frame was drawn (with ``camera``): its empty slots were skipped by the
        tier; the next frame's origin is the one nearer where this camera looked."""
        self.padding_draws += self._padding
        if camera is not None:
            self.focus = np.asarray(camera.target, np.float64).copy()
        self._undrawn = []

    # ------------------------------------------------------------------ render -> map stage
    def publish(self, views: list) -> None:
        """Tell the map stage where the views look: ``[(name, camera, width, height), ...]``,
        the main view first. Sent when a camera changed, at most every
        :data:`CAMERA_PERIOD_S` while it keeps moving (an orbiting camera would otherwise make
        the map stage select again for every frame); the render loop calls this each turn, so
        the last camera of a move goes out within a period."""
        cams = [mr.camera_dict(n, c, w, h) for n, c, w, h in views if c is not None]
        if not cams or cams == self._last_cams:
            return
        now = time.monotonic()
        if now - self._t_cams < CAMERA_PERIOD_S:
            return
        self._last_cams, self._t_cams = cams, now
        self._send({"type": "cameras", "views": cams})

    def publish_stage(self, stage) -> None:
        """The render stage's views: main (the window's camera or the last drawn), then the
        view server's views (render/view/hub.py), each with the camera it last drew."""
        main = stage.window.camera if getattr(stage, "window", None) is not None else stage.view.last
        views = [("main", main, stage.view.cfg.render.size[0], stage.view.cfg.render.size[1])]
        hub = getattr(stage, "hub", None)
        for vid, v in (getattr(hub, "views", None) or {}).items():
            views.append((str(vid), getattr(v.ctl, "last", None), int(v.width), int(v.height)))
        self.publish(views)

    # ------------------------------------------------------------------ picking, stats
    def is_map_slot(self, slot) -> bool:
        return slot is not None and int(slot) >= self.ring_cap

    def point(self, slot: int) -> Optional[dict]:
        """A picked map point: world position (float64, from the region), channels, its file."""
        i = int(slot) - self.ring_cap
        if self.region is None or not 0 <= i < self.slots or not self.occupied[i]:
            return None
        r = self.region
        fi = int(r.file[i])
        name = self.files[fi] if fi < len(self.files) else "?"
        chans = {k: (v[i].tolist() if v.ndim > 1 else float(v[i])) for k, v in r.channel.items()}
        return {"slot": int(slot), "position": [float(v) for v in r.positions[i]], "channels": chans,
                "source": f"map: {name}", "map_slot": i}

    def pick_reply(self, ring, slot, point_to_dict) -> dict:
        """The render stage's pick answer: a map point named ``map: <file>``, or a live point
        named by its source (the ``source_index`` channel with several sources)."""
        if slot is None:
            return {"point": None}
        if self.is_map_slot(slot):
            p = self.point(slot)
            return {"point": p, "source": p["source"] if p else None}
        p = point_to_dict(ring.get_point(slot))
        if p is not None:
            si = p["channels"].get("source_index")
            names = self.source_names
            if si is not None and 0 <= int(si) < len(names):
                p["source"] = names[int(si)]
            elif len(names) == 1:
                p["source"] = names[0]
        return {"point": p, "source": p.get("source") if p else None}

    @property
    def empty_slots(self) -> int:
        """Slots of the last composed frame that hold no point (its ``size`` counts every slot:
        the ring's empty ones and the map's padding)."""
        return max(int(self._padding), 0)

    def stats(self) -> dict:
        return {"map_points": int(self.points), "map_nodes": int(self.nodes), "map_version": int(self.version),
                "map_versions_taken": int(self.versions), "map_bad_messages": int(self.bad_messages),
                "map_slots": int(self.slots), "map_preview": self.preview, "map_previews_taken": int(self.previews)}

    def close(self) -> None:
        self.pull.close(0)
        self.push.close(0)
        if self.region is not None:
            self.region.close()


def _units(u) -> Optional[dict]:
    """The map stage's ``{"xy", "z"}`` labels, or None for anything else (a view shows metres)."""
    if isinstance(u, dict) and all(isinstance(u.get(k), str) and len(u[k]) <= 16 for k in ("xy", "z")):
        return {"xy": u["xy"], "z": u["z"]}
    return None


def occupied_ranges(head: int, size: int, capacity: int) -> list[tuple[int, int]]:
    """The ring's occupied slots [head, head + size) modulo capacity as <= 2 ranges."""
    if size <= 0:
        return []
    if size >= capacity:
        return [(0, capacity)]
    end = head + size
    return [(head, end)] if end <= capacity else [(head, capacity), (0, end - capacity)]


def xor_ranges(a: list, b: list) -> list[tuple[int, int]]:
    """Slots in exactly one of two range lists (each non-overlapping)."""
    cuts = sorted({x for r in a + b for x in r})
    out = []
    inside = lambda rs, x: any(p <= x < q for p, q in rs)
    for lo, hi in zip(cuts, cuts[1:]):
        if inside(a, lo) != inside(b, lo):
            out.append((lo, hi))
    return out
