"""The map stage: serves a ``map:`` block's files to the render stage, view by view.

It opens the files (COPC through its own hierarchy, others through their level-of-detail
index, :mod:`pointflow.map`), takes the render stage's cameras (every view's; the main view
first), chooses nodes by projected size within ``map.point_budget``, coarse first, loads them
(decoded nodes are kept in a bounded cache) and puts their points into the map region
(:mod:`pointflow.render.mapregion`), a version at a time: loading happens here, in its own
process, so a camera move never stalls a frame. While the camera is still it goes on
refining; nodes that left every view are cleared. A bad file is a one-line error, counted
(``map_error``), and the stage idles: the live part of the pipeline goes on.
"""
from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any, Optional

import numpy as np
import zmq

from ..stage.kinds import StageKind, register_stage_kind
from ..arrays import rgb_u8
from ..render import mapregion as mr
from .config import MapConfig

#: Starts after the render stage (it binds the map endpoint this stage connects to) and
#: before the cadence; stops with the render stage. Running totals: its reads and moves.
KIND = register_stage_kind(StageKind(
    name="map", main="pointflow.map.process:main", start_order=15, stop_wave=2,
    counters=("map_nodes_loaded", "map_camera_moves", "map_cache_hits", "map_cache_misses", "map_versions"),
    accounting="pointflow.map.process:accounting", wanted="pointflow.map.process:wanted"))

#: Default viewport of the first selection, before the render stage sent a camera.
FIRST_VIEWPORT = (1280, 720)


def kept_channels(cfg, mc: MapConfig, available: list[str]) -> list[tuple[str, str, int]]:
    """The channels the map region carries: ``map.channels`` (or, by default, the ring's
    channels, which are those the render stage draws) that the map has."""
    want = list(mc.channels) if mc.channels is not None else list(cfg.ring_channels())
    return [mr.channel_spec(c) for c in want if c in available]


class _Opener(threading.Thread):
    """``open_map`` off the stage loop: building an index may take minutes, and the loop must
    keep beating meanwhile (the progress line comes from the index builder)."""

    def __init__(self, mc: MapConfig, log, counters=None, preview=None):
        super().__init__(name="pointflow-map-open", daemon=True)
        self.mc, self.log, self.counters, self.preview = mc, log, counters, preview
        self.source: Any = None
        self.error: Optional[BaseException] = None

    def run(self) -> None:
        from . import open_map

        progress = index_progress(self.log, self.counters)
        try:
            pv = self.preview
            self.source = open_map(self.mc.paths(), cache_dir=self.mc.cache_dir, progress=progress,
                                   preview=pv.offer if pv is not None else None,
                                   preview_points=min(int(self.mc.point_budget), PREVIEW_POINTS))
        except BaseException as exc:  # noqa: BLE001 - reported by the stage loop
            self.error = exc


def index_progress(log, counters=None):
    """The index build's ``progress(done, total)`` in the map stage: ``map_index_pct`` for the
    run's live line (``map: indexing 35%``) and a log line per tenth,
    ``map index: 90% (627949 of 697721 points, about 3 s left)``: the percentage of the points
    counted, rounded down, 100 % only once the index is in place; the time left from the rate
    so far (as the command line's progress line gives it)."""
    last = [-1]
    t0 = time.monotonic()

    def progress(done: int, total: int) -> None:
        pct = min(100, int(100 * done / max(total, 1)))
        if counters is not None:
            counters.extra["map_index_pct"] = pct
        if pct // 10 != last[0]:
            last[0] = pct // 10
            el = time.monotonic() - t0
            left = f", about {el * (total - done) / done:.0f} s left" if 0 < done < total and el > 0.5 else ""
            log.info("map index: %d%% (%d of %d points%s)", pct, done, total, left)

    return progress


def _error_line(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}" if not isinstance(exc, ValueError) else str(exc)


#: Points of a map drawn at most while its index is built (preview.py), within the budget.
PREVIEW_POINTS = 100_000

#: While the camera keeps moving (cameras less than :data:`MOVING_GAP_S` apart), nodes are
#: chosen again at most this often, so an orbiting view does not swap nodes at every camera
#: message; a single move is chosen for at once.
MOVING_SELECT_S = 0.4
MOVING_GAP_S = 0.25

#: Nodes the loader thread is asked for ahead of placing them.
LOADS_IN_FLIGHT = 4


class _Loader(threading.Thread):
    """Reads nodes (through the cache) in its own thread: ``ask(key)``; results in ``done`` as
    ``(key, data, error, t0_ns, t1_ns, from_cache)``. ``MapSource.load`` and the cache are
    thread-safe."""

    def __init__(self, source, cache):
        super().__init__(name="pointflow-map-load", daemon=True)
        import queue

        self.src, self.cache = source, cache
        self.q: "queue.Queue" = queue.Queue()
        self.done: deque = deque()

    def ask(self, key) -> None:
        self.q.put(key)

    def stop(self) -> None:
        self.q.put(None)

    def run(self) -> None:
        while True:
            key = self.q.get()
            if key is None:
                return
            t0 = time.monotonic_ns()
            data = self.cache.get(key)
            cached = data is not None
            err = None
            if data is None:
                try:
                    data = self.src.load(key)
                    self.cache.put(key, data)
                except ValueError as exc:
                    err = exc
                except Exception as exc:  # noqa: BLE001 - named by the stage loop, the stage goes on
                    err = exc
            self.done.append((key, data, err, t0, time.monotonic_ns(), cached))


class Server:
    """Selection, loading and slot bookkeeping of one open map."""

    def __init__(self, ctx, source, region: mr.MapRegion, files: list[str], first_version: int = 0,
                 held: Optional[np.ndarray] = None, units: Optional[dict] = None):
        """``first_version``/``held``: a preview's last version and the slots it holds in
        ``region`` (free again once this server's first, full, version is acknowledged);
        ``units``: the map's length units (source.py ``header_units``), sent with each version."""
        from . import NodeCache

        self.ctx, self.src, self.region, self.files, self.units = ctx, source, region, files, units
        mc = ctx.cfg.map
        self.mc = mc
        self.budget = int(mc.point_budget)
        self.cache = NodeCache(int(mc.cache_mb * 2 ** 20))
        self.free = np.ones(region.slots, bool)  # slots nobody holds (a mask: freeing is O(n), not a merge)
        self.n_free = int(region.slots)
        self.pending_free: list[tuple[int, np.ndarray]] = []  # (version that cleared them, slots)
        self.published: dict[Any, np.ndarray] = {}  # node key -> its slots
        self.node_ranges: dict[Any, dict[str, tuple[float, float]]] = {}
        self.bad_nodes: set = set()
        self.cameras: list[dict] = []
        self.cap: dict[Any, int] = {}  # nodes drawn in part (a root bigger than the budget)
        self.want: list = []
        self.want_stale = True
        self.t_selected = 0.0  # monotonic s of the last selection
        self.moving = False  # the last camera came hard on the one before (an orbit, a drag)
        self.version = int(first_version)
        self.acked = -1
        if held is not None and held.size:
            self.free[held] = False
            self.n_free -= int(held.size)
            self.pending_free.append((self.version + 1, held))
        self.full_next = True
        self.set_ranges: list = []
        self.cleared_ranges: list = []
        self.load_ms: deque[float] = deque(maxlen=256)
        self.inflight: set = set()
        self.ready: dict[Any, dict] = {}
        self.loader = _Loader(source, self.cache)
        self.loader.start()
        self.t_camera_ns = 0
        self.t_refined_ns = 0
        self.refine_ms: Optional[float] = None
        c = ctx.counters
        c.extra.update(map_nodes=0, map_points=0, map_nodes_loaded=0, map_cache_bytes=0,
                       map_cache_mb=float(mc.cache_mb), map_files=files, map_point_count=int(source.point_count))

    # ------------------------------------------------------------------ messages
    def on_message(self, msg: dict) -> None:
        t = msg.get("type")
        if t == "cameras" and isinstance(msg.get("views"), list):
            cams = [v for v in msg["views"] if isinstance(v, dict)]
            if cams != self.cameras:
                now_ns = time.monotonic_ns()
                self.moving = self.t_camera_ns > 0 and (now_ns - self.t_camera_ns) < MOVING_GAP_S * 1e9
                self.cameras = cams
                self.want_stale = True
                self.t_camera_ns = now_ns
                self.refine_ms = None
                c = self.ctx.counters.extra
                c["map_camera_moves"] = c.get("map_camera_moves", 0) + 1
                c["map_refine_ms"] = None
        elif t == "ack":
            self.acked = max(self.acked, int(msg.get("version", -1)))
            keep = []
            for v, slots in self.pending_free:
                if v <= self.acked:
                    self.free[slots] = True
                    self.n_free += int(slots.size)
                else:
                    keep.append((v, slots))
            self.pending_free = keep
        elif t == "hello":  # a (new) render stage: everything again
            self.full_next = True
        else:
            self.ctx.counters.drop("bad_message", 1)

    # ------------------------------------------------------------------ selection
    def _camera_list(self) -> list[dict]:
        if self.cameras:
            return self.cameras
        from ..render.camera import Camera

        lo, hi = (np.asarray(b, np.float64) for b in self.src.bounds)
        w, h = FIRST_VIEWPORT
        cam = Camera.fit(lo, hi, aspect=w / h)
        return [mr.camera_dict("main", cam, w, h)]

    def select(self) -> None:
        """Nodes every view wants, merged round-robin (main view first) within the budget."""
        from ..render.camera import Camera
        from . import select_nodes

        loaded = set(self.published)
        lists, views = [], []
        for v in self._camera_list():
            cam = Camera(eye=v["eye"], target=v["target"], up=v["up"], fov_deg=v["fov_deg"], near=v["near"],
                         far=v["far"])
            w, h = int(v["width"]), int(v["height"])
            views.append((cam.view_proj(w, h), (w, h), cam.eye))
            lists.append(list(select_nodes(self.src, *views[-1], self.budget, loaded)))
        merged, seen, total = [], set(), 0
        for i in range(max((len(x) for x in lists), default=0)):
            for lst in lists:
                if i < len(lst) and lst[i] not in seen and lst[i] not in self.bad_nodes:
                    n = int(self.src.node(lst[i]).count)
                    if total + n > self.budget:
                        continue
                    seen.add(lst[i])
                    merged.append(lst[i])
                    total += n
        self.cap = {}
        if not merged:  # every root in view holds more than the budget: a spread subset of them
            roots = [k for k in self.src.root_keys() if k not in self.bad_nodes
                     and any(k in select_nodes(self.src, v, wh, e, 1 << 62, ()) for v, wh, e in views)]
            for k in roots:
                self.cap[k] = self.budget // len(roots)
            merged = roots
        self.want = merged
        self.want_stale = False
        self.t_selected = time.monotonic()

    # ------------------------------------------------------------------ loading
    def _collect(self) -> None:
        """Take what the loader finished: count it, trace it, keep it for placing."""
        from ..chunk import new_trace_id

        c = self.ctx.counters
        while self.loader.done:
            key, data, err, t0, t1, cached = self.loader.done.popleft()
            self.inflight.discard(key)
            if err is not None:  # MapError: a broken node, named; the rest of the map goes on
                self.bad_nodes.add(key)
                c.drop("map_node_error", 1)
                self.ctx.log.error("map node %s not loaded: %s", key, _error_line(err))
                continue
            if not cached:
                n = int(len(data["positions"]))
                self.load_ms.append((t1 - t0) / 1e6)
                c.points_in += n
                c.extra["map_nodes_loaded"] = c.extra.get("map_nodes_loaded", 0) + 1
                self.ctx.spans.record(new_trace_id(), "map_load", t0, t1, n)
            self.ready[key] = data

    def step(self, deadline_ns: int) -> bool:
        """Clear what no view wants, ask the loader for wanted nodes (coarse first, a few in
        flight), place what it finished until the deadline; publish a version when anything
        changed. True while nodes are still to load. Loads run in the loader thread, so a slow
        read (or a kernel compiled on first use) never keeps this loop from beating."""
        if self.want_stale and (not self.moving or time.monotonic() - self.t_selected >= MOVING_SELECT_S):
            self.select()
        want = set(self.want)
        for key in [k for k in self.published if k not in want]:
            slots = self.published.pop(key)
            self.node_ranges.pop(key, None)
            self.cleared_ranges += mr.runs(slots)
            self.pending_free.append((self.version + 1, slots))
        for key in [k for k in self.ready if k not in want]:
            del self.ready[key]  # left the view while it loaded (it stays in the cache)
        todo = [k for k in self.want if k not in self.published and k not in self.bad_nodes]
        for key in todo:
            if len(self.inflight) >= LOADS_IN_FLIGHT:
                break
            if key not in self.inflight and key not in self.ready:
                self.inflight.add(key)
                self.loader.ask(key)
        self._collect()
        starved = False
        for key in todo:
            if time.monotonic_ns() > deadline_ns and (self.set_ranges or self.cleared_ranges):
                break
            data = self.ready.get(key)
            if data is None:
                continue
            n = min(int(len(data["positions"])), self.cap.get(key, 1 << 62))
            if n > self.n_free:
                starved = True
                break  # slots come back when the render stage acknowledges what was cleared
            del self.ready[key]
            self._place(key, data, self.cap.get(key))
        busy = self.want_stale or any(k not in self.published for k in self.want if k not in self.bad_nodes)
        # a full version replaces what the render stage shows (a preview too): not an empty one
        # while the first nodes are still being read
        if self.set_ranges or self.cleared_ranges or (self.full_next and (self.published or not busy or starved)):
            self._publish()
        if not busy and self.refine_ms is None and self.t_camera_ns:
            self.refine_ms = (time.monotonic_ns() - self.t_camera_ns) / 1e6
            self.ctx.counters.extra["map_refine_ms"] = round(self.refine_ms, 1)
        return busy

    def close(self) -> None:
        self.loader.stop()

    def _place(self, key, data: dict, cap: Optional[int] = None) -> None:
        pos = np.asarray(data["positions"], np.float64)
        take = None
        if cap is not None and cap < pos.shape[0]:  # a root bigger than the budget: evenly spread
            take = np.linspace(0, pos.shape[0] - 1, cap).astype(np.int64)
            pos = pos[take]
        n = pos.shape[0]
        slots = np.flatnonzero(self.free)[:n].astype(np.int32)  # the lowest free slots, ascending
        self.free[slots] = False
        self.n_free -= n
        r = self.region
        r.positions[slots] = pos
        r.file[slots] = int(key[0])  # the file index of the node (map keys: file, depth, x, y, z)
        ranges = {}
        for name, arr in r.channel.items():
            v = data.get(name)
            if v is None:
                arr[slots] = 0 if arr.dtype.kind == "u" else np.nan
                continue
            v = np.asarray(v) if take is None else np.asarray(v)[take]
            if name == "rgb" and v.dtype.itemsize > 1:  # 16-bit LAS colour, as the ring takes it
                v = rgb_u8(v)  # (0..255 kept: many LAS files use only that range)
            arr[slots] = v.reshape(arr[slots].shape).astype(arr.dtype, copy=False)
            if arr.ndim == 1 and n:
                fv = np.asarray(arr[slots], np.float64)
                fv = fv[np.isfinite(fv)]
                if fv.size:
                    ranges[name] = (float(fv.min()), float(fv.max()))
        self.published[key] = slots
        self.node_ranges[key] = ranges
        self.set_ranges += mr.runs(slots)

    def _publish(self) -> None:
        self.version += 1
        full = self.full_next
        if full:
            occupied = np.sort(np.concatenate(list(self.published.values()))) if self.published else np.zeros(0)
            set_r, cleared = mr.runs(occupied), []
        else:
            set_r, cleared = self.set_ranges, self.cleared_ranges
        ranges: dict[str, list] = {}
        for rr in self.node_ranges.values():
            for k, (lo, hi) in rr.items():
                cur = ranges.get(k)
                ranges[k] = [lo, hi] if cur is None else [min(cur[0], lo), max(cur[1], hi)]
        points = int(sum(s.size for s in self.published.values()))
        r = self.region
        lo, hi = (np.asarray(b, np.float64) for b in self.src.bounds)
        origin = getattr(self.src, "origin", None)
        origin = (lo + hi) / 2 if origin is None else np.asarray(origin, np.float64)
        msg = {"type": "version", "version": self.version, "full": full, "region": r.path, "slots": r.slots,
               "channels": [list(c) for c in r.channels], "files": self.files,
               "origin": [float(v) for v in origin], "bounds": [lo.tolist(), hi.tolist()], "set": set_r, "cleared": cleared, "points": points,
               "nodes": len(self.published), "channel_ranges": ranges, "units": self.units}
        try:
            self.ctx_push.send(mr.encode(msg), zmq.NOBLOCK)
        except zmq.Again:  # render not there (yet): everything again once it says hello
            self.full_next = True
            self.version -= 1
            return
        self.full_next = False
        self.set_ranges, self.cleared_ranges = [], []
        c = self.ctx.counters
        c.points_out += sum(int(b) - int(a) for a, b in set_r)  # points handed to the render stage, in all
        c.extra["map_versions"] = c.extra.get("map_versions", 0) + 1
        lm = sorted(self.load_ms)
        c.extra.update(map_nodes=len(self.published), map_points=points, map_version=self.version,
                       map_cache_bytes=int(self.cache.bytes_used), map_cache_hits=int(self.cache.hits),
                       map_cache_misses=int(self.cache.misses),
                       map_load_ms_p50=round(lm[len(lm) // 2], 2) if lm else None,
                       map_load_ms_max=round(lm[-1], 2) if lm else None)


def accounting(stages: dict, ring=None, cfg=None) -> dict:
    """``stats()["accounting"]`` for the map (docs/map.md): the points the map stage holds in
    the region (``map_points_held``, the sum of its published nodes) and the points the render
    stage took into its map slots (``map_points_drawn``); ``map_agrees`` compares them when
    both have reported the same version (None while a version is in flight, and while the map
    is not open yet: a preview of it is drawn then, preview.py)."""
    m, r = stages.get("map") or {}, stages.get("render") or {}
    held, drawn = m.get("map_points"), r.get("map_points")
    same = (m.get("map_version") is not None and m.get("map_version") == r.get("map_version")
            and bool(m.get("map_ready")))
    return {"map_file_points": m.get("map_point_count"), "map_points_loaded": m.get("points_in", 0),
            "map_points_held": held, "map_points_drawn": drawn,
            "map_agrees": (held == drawn) if same else None, "map_error": m.get("map_error")}


def wanted(cfg) -> bool:
    """A run has the map stage when its config has a ``map:`` block."""
    return getattr(cfg, "map", None) is not None


def _sweep_regions(run_dir: str) -> None:
    """Remove the regions of map stages that died (a restarted stage makes a new one; a
    render stage still mapping the old one keeps its pages until it lets go)."""
    import glob
    import os

    from ..ring.sweep import pid_alive

    for p in glob.glob(os.path.join(run_dir, "map-region-*")):
        try:
            pid = int(os.path.basename(p).split("-")[2])
        except (IndexError, ValueError):
            continue
        if pid != os.getpid() and not pid_alive(pid):
            try:
                os.unlink(p)
            except OSError:
                pass


def _send_bounds(push, files: list[str], bounds=None, units=None):
    """The map's bounds (and length units) to the render stage, as soon as its headers say
    them (None: unknown)."""
    from .source import header_bounds

    bounds = header_bounds(files) if bounds is None else bounds
    if bounds is not None:
        try:
            push.send(mr.encode({"type": "bounds", "bounds": [bounds[0].tolist(), bounds[1].tolist()],
                                 "files": files, "units": units}), zmq.NOBLOCK)
        except zmq.Again:
            pass
    return bounds


def main(ctx) -> None:
    cfg = ctx.cfg
    mc: MapConfig = cfg.map
    c = ctx.counters
    pull = ctx.zmq.socket(zmq.PULL)
    pull.setsockopt(zmq.LINGER, 0)
    pull.bind(ctx.endpoints.map_camera)
    push = ctx.zmq.socket(zmq.PUSH)
    push.setsockopt(zmq.LINGER, 0)
    push.setsockopt(zmq.SNDHWM, 1000)
    push.connect(ctx.endpoints.map)
    files = mc.paths()
    _sweep_regions(ctx.info.run_dir)
    c.extra.update(map_files=files, map_error=None, map_ready=False)
    t_start = time.monotonic()
    from .source import header_units

    # the user's word, else the CRS: a map in feet is labelled in feet
    units = {"xy": mc.units, "z": mc.units} if mc.units is not None else header_units(files, ctx.log)
    bounds = _send_bounds(push, files, units=units)  # from the headers: the views frame the map before it is open
    from .preview import Preview

    preview = Preview(ctx, mc.point_budget, lambda avail: kept_channels(cfg, mc, avail), bounds, files, push, units)
    opener = _Opener(mc, ctx.log, c, preview)
    opener.start()
    cams_msg = None  # the views' cameras while the map opens, for the server to start from
    server: Optional[Server] = None
    region: Optional[mr.MapRegion] = None
    try:
        while ctx.running:
            ctx.beat()
            if server is None:
                if opener.is_alive():
                    while pull.poll(0, zmq.POLLIN):  # a (new) render stage says hello: the bounds again
                        msg = mr.decode(pull.recv())
                        if msg is not None and msg.get("type") == "hello":
                            bounds = _send_bounds(push, files, bounds, units)
                            preview.full_next = True
                        elif msg is not None and msg.get("type") == "cameras":
                            cams_msg = msg
                    preview.step()  # what the index build has read so far, drawn while it goes on
                    ctx.sleep(0.05)
                    continue
                if opener.error is not None or opener.source is None:
                    exc = opener.error or ValueError("open_map returned nothing")
                    if c.extra.get("map_error") is None:  # one line, once; the live part goes on
                        line = _error_line(exc)
                        ctx.log.error("map not shown: %s", line)
                        c.extra["map_error"] = line
                        c.drop("map_error", 1)
                        try:  # the views stop framing a map that is not there
                            push.send(mr.encode({"type": "bounds", "bounds": None}), zmq.NOBLOCK)
                        except zmq.Again:
                            pass
                        preview.clear()  # nor show the part of it read before the error
                    while pull.poll(0, zmq.POLLIN):
                        pull.recv()
                    ctx.sleep(0.1)
                    continue
                src = opener.source
                chans = kept_channels(cfg, mc, list(getattr(src, "channels", [])))
                preview.step()
                held = None
                if preview.region is not None and preview.region.channels == chans:  # the preview's region goes on
                    region, held = preview.region, preview.held()
                else:
                    if preview.region is not None:  # the render stage keeps its mapping until it takes the new one
                        preview.region.close()
                        preview.region.unlink()
                    region = mr.MapRegion.create(ctx.info.run_dir, mc.point_budget, chans)
                server = Server(ctx, src, region, list(src.paths), first_version=preview.version, held=held, units=units)
                server.ctx_push = push
                if cams_msg is not None:
                    server.on_message(cams_msg)
                c.extra.update(map_ready=True, map_open_s=round(time.monotonic() - t_start, 3), map_index_pct=None)
                ctx.log.info("map open: %s (%d points, channels %s)", ", ".join(files), int(src.point_count),
                             [ch[0] for ch in chans] or "none")
            busy = server.step(time.monotonic_ns() + int(mc.load_slice_ms * 1e6))
            timeout = 5 if busy else 50
            if pull.poll(timeout, zmq.POLLIN):
                while pull.poll(0, zmq.POLLIN):
                    msg = mr.decode(pull.recv())
                    if msg is None:
                        c.drop("bad_message", 1)
                    else:
                        server.on_message(msg)
    finally:
        if server is not None:
            server.close()
        pull.close(0)
        push.close(0)
        if region is None:
            region = preview.region  # stopped while the index was being built
        if region is not None:
            region.close()
            region.unlink()
        if opener.is_alive():  # stopped while the index was being built: its half-built folder goes too
            from .build import remove_unfinished

            for d in remove_unfinished():
                ctx.log.info("index build stopped; removed its unfinished folder %s", d)
