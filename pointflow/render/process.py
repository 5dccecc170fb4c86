"""The render stage: receive slab handoffs, draw them with the chosen tier, write PNGs.

Per handoff: build a :class:`FrameInput` over the slab (no copy), update the camera,
``renderer.render()``, give the slab back at once (tiers copy what they keep), record
spans, and every ``output.every_n_frames`` frames read the image back and save a PNG.
"""
from __future__ import annotations

import dataclasses
import glob
import json
import os
import time
from typing import Any, Optional

import numpy as np
import zmq

from ..ring import PointRing
from ..ring.handoff import SlabReader
from ..ring.slabs import SlabPair
from ..runtime.kinds import StageKind, register_stage_kind
from ..runtime.stage import StageContext
from .base import FrameInput, RenderError, Renderer
from . import control
from .camera import Camera, clip_planes, scene_box
from .control import ControlError, ViewState, style_render_config


class CameraController:
    """Frames the scene automatically (``camera.mode: auto``/``orbit``) or uses the fixed
    camera from the config. Bounds come from a strided sample of the occupied slots, checked
    about once a second (not every frame); the camera refits when they changed by more than
    10%, so it follows a growing map or a moving sensor without jitter. With a map, the live
    points' box and the map's are kept apart: the camera frames the map when the two lie far
    apart (``apart_m``), and near and far planes follow what lies in front of the camera."""

    def __init__(self, ctx_cfg, width: int, height: int):
        self.cfg = ctx_cfg.render.camera
        self.aspect = width / max(height, 1)
        self.camera: Optional[Camera] = None
        self._last_fit = 0.0
        self._box = None
        self._clip = None  # the live points' min/max box (with a margin): what the planes must hold
        self.map_box = None
        self.apart_m = 0.0  # how far apart map and live points are (0: not apart)
        self._t0 = time.monotonic()
        if self.cfg.mode == "fixed":
            self.camera = Camera(eye=self.cfg.position, target=self.cfg.target, up=self.cfg.up,
                                 fov_deg=self.cfg.fov_deg, near=self.cfg.near, far=self.cfg.far)

    @staticmethod
    def _bounds(frame: FrameInput, clip: bool = False):
        """1st-99th percentile box of a strided sample of the occupied live slots (world
        coords); ``clip``: also the min/max box of every occupied slot, widened by a tenth (what
        must not be clipped; about once a second)."""
        slots = frame.occupied_slots()
        if frame.live_slots is not None:
            slots = slots[slots < frame.live_slots]
        step = max(1, slots.size // 50_000)
        p = frame.positions[slots[::step]].astype(np.float64)
        p = p[np.isfinite(p).all(axis=1)]
        if not p.size:
            return (None, None) if clip else None
        lo, hi = np.percentile(p, [1, 99], axis=0)
        box = (lo + frame.origin, hi + frame.origin)
        if not clip:
            return box
        if step > 1:  # the planes must hold every point, not the sample's: sparse far returns too
            ext = CameraController._extent(frame)
            if ext is None:  # some position is not finite: those rows are left out
                q = frame.positions[slots]
                q = q[np.isfinite(q).all(axis=1)]
                ext = q.min(axis=0).astype(np.float64), q.max(axis=0).astype(np.float64)
            mlo, mhi = ext
        else:
            mlo, mhi = p.min(axis=0), p.max(axis=0)
        pad = 0.1 * (mhi - mlo) + 0.5
        return box, (mlo - pad + frame.origin, mhi + pad + frame.origin)

    @staticmethod
    def _extent(frame: FrameInput):
        """Min and max of every occupied live slot's position, read in place over the (at
        most two) slot ranges and column by column: a min over axis 0 of a gathered (n, 3)
        copy took 40-130 ms for 300k points here, in the render loop once a second per view
        (a turn arriving then waited for it: the drag's tail, bench/bench_drag.py); this takes
        about 1 ms. None when some position is not finite (the caller leaves those rows out)."""
        cap = max(int(frame.capacity), 1)
        a, n = int(frame.head) % cap, int(frame.size)
        ranges = [(a, min(a + n, cap))] + ([(0, a + n - cap)] if a + n > cap else [])
        if frame.live_slots is not None:
            ranges = [(lo, min(hi, int(frame.live_slots))) for lo, hi in ranges]
        blocks = [frame.positions[lo:hi] for lo, hi in ranges if hi > lo]
        if not blocks or not all(np.isfinite(b).all() for b in blocks):
            return None
        lo = np.array([min(float(b[:, j].min()) for b in blocks) for j in range(3)], np.float64)
        hi = np.array([max(float(b[:, j].max()) for b in blocks) for j in range(3)], np.float64)
        return lo, hi

    def _moved(self, box) -> bool:
        """Refit only when the data's box changed by more than 10% of its size (no jitter)."""
        lo0, hi0 = self._box
        diag = max(float(np.linalg.norm(hi0 - lo0)), 1e-9)
        return max(float(np.abs(box[0] - lo0).max()), float(np.abs(box[1] - hi0).max())) > 0.1 * diag

    def refresh(self, frame: FrameInput) -> None:
        """Keep the data box current (about once a second; refit only on a >10% change)."""
        now = time.monotonic()
        if frame.map_box is not None:
            self.map_box = frame.map_box
        if frame.size and (self._box is None or now - self._last_fit > 1.0):
            self._last_fit = now
            box, self._clip = self._bounds(frame, clip=True)
            if box is not None and (self._box is None or self._moved(box)):
                self._box = box
        self.apart_m = scene_box(self._box, self.map_box)[1]  # a user's camera is warned too

    def clip_boxes(self) -> list:
        """What near and far must hold: the live points' box and the map's."""
        return [self._clip, self.map_box]

    def planes(self, eye, target, up, fov_deg: float) -> tuple[float, float]:
        return clip_planes(eye, target, up, fov_deg, self.aspect, self.clip_boxes())

    def update(self, frame: FrameInput) -> Optional[Camera]:
        c = self.cfg
        if c.mode == "fixed":
            return self.camera
        self.refresh(frame)
        box, self.apart_m = scene_box(self._box, self.map_box)
        if box is None:
            return None
        now = time.monotonic()
        az = -60.0 + (c.orbit_deg_per_s * (now - self._t0) if c.orbit_deg_per_s else 0.0)
        cam = Camera.fit(box[0], box[1], fov_deg=c.fov_deg, azimuth_deg=az,
                         elevation_deg=c.elevation_deg, up=c.up, aspect=self.aspect)
        if c.position is not None:
            cam.eye = np.asarray(c.position, np.float64)
        if c.target is not None:
            cam.target = np.asarray(c.target, np.float64)
        cam.near, cam.far = self.planes(cam.eye, cam.target, cam.up, cam.fov_deg)
        self.camera = cam
        return cam


class SourceMask:
    """Hides the points of some sources: a render-private copy of the positions with NaN where
    a hidden source's points are (every tier skips non-finite positions), kept up to date
    range by range with the handoffs' dirty ranges; a change of the hidden set re-uploads the
    whole slab once. Costs one positions array (12 B a slot) while something is hidden."""

    def __init__(self, names: list[str]):
        self.names = names
        self.pos: Optional[np.ndarray] = None
        self.ids: Optional[np.ndarray] = None  # the hidden sources' indices
        self.hidden_draws = 0  # point-draws not made because hidden (kept out of nonfinite_skipped)

    def apply(self, frame: FrameInput, hidden: list[str]) -> FrameInput:
        ids = np.array(sorted(self.names.index(h) for h in hidden if h in self.names), np.float32)
        src = frame.channels.get(control.SOURCE_CHANNEL)
        if src is None or (not ids.size and self.ids is None):
            return frame
        if not ids.size:  # shown again: the slab's own positions, all of them once
            self.pos, self.ids = None, None
            frame.dirty = None
            return frame
        full = self.ids is None or not np.array_equal(ids, self.ids) or frame.dirty is None
        if self.pos is None:
            self.pos = np.empty_like(frame.positions)
        ranges = [(0, frame.capacity)] if full else frame.dirty
        for a, b in ranges:
            p = self.pos[a:b]
            p[:] = frame.positions[a:b]
            p[np.isin(src[a:b], ids)] = np.nan
        if full:
            frame.dirty = None
        self.ids = ids
        occ = frame.occupied_slots()
        self.hidden_draws += int(np.count_nonzero(np.isin(src[occ], ids)))
        frame.positions = self.pos
        return frame


class FollowFrame:
    """The transforms the sources send (a copy of what ingest gets, only with ``frames.fixed``),
    so the camera can follow a frame: where that frame's origin is in the fixed frame now."""

    def __init__(self, fixed: str, sock):
        from ..frames.buffer import TransformBuffer

        self.fixed = fixed
        self.sock = sock
        self.buf = TransformBuffer()
        self.bad = 0

    def drain(self) -> None:
        from ..frames import message as tfmsg
        from ..frames.buffer import FrameError

        while self.sock.poll(0, zmq.POLLIN):
            try:
                batch = tfmsg.decode(json.loads(self.sock.recv()))
                for t in batch.transforms:
                    self.buf.set_transform(t.parent, t.child, t.stamp_ns, t.translation, t.rotation, t.static)
            except (ValueError, FrameError):  # ingest counts and reports bad transforms; here they are skipped
                self.bad += 1

    def origin(self, frame: str) -> Optional[np.ndarray]:
        """The origin of ``frame`` in the fixed frame at the newest time known, or None."""
        if frame == self.fixed:
            return np.zeros(3)
        try:
            _, t = self.buf.lookup(self.fixed, frame, self.buf.newest_of_chain(self.fixed, frame) or 0)
        except Exception:  # noqa: BLE001 - not (yet) connected to the fixed frame
            return None
        return np.asarray(t, np.float64)


def _window_control(view: "ViewController", msg: dict, window, ctx) -> None:
    """The window's mouse and wheel, as control messages: the same path as Python's."""
    try:
        view.apply(msg, window)
    except control.ControlError as exc:  # e.g. a turn before anything was framed
        ctx.log.debug("window: %s", exc)


class ViewController:
    """The render stage's view: the control state (:mod:`pointflow.render.control`), the
    camera it gives each frame, and whether a frame would look like the last one drawn
    (then it is not drawn: an idle pipeline costs the render stage next to no CPU)."""

    def __init__(self, cfg, width: int, height: int, channels: list[str]):
        self.cfg = cfg
        self.auto = CameraController(cfg, width, height)
        self.state = ViewState.from_render_config(cfg.render)
        if isinstance(cfg.view, dict) and cfg.view.get("hidden_sources"):
            self.state.hidden_sources = list(cfg.view["hidden_sources"])
        self.mask = SourceMask([s.name for s in cfg.sources])
        self.follow: Optional[FollowFrame] = None  # set by main() when frames.fixed is set
        # True once a control message set or turned the camera, or a `view:` block set it
        self.user_camera = bool(isinstance(cfg.view, dict) and isinstance(cfg.view.get("camera"), dict))
        self.channels = channels
        self.height = height
        self.last: Optional[Camera] = None  # the camera of the last frame drawn
        self.drawn_version = -1
        self.changed_ns = 0  # when the newest version was applied
        self.drawn_ns = 0  # when the frame that first showed drawn_version was done
        self._drawn_key = None
        self.skipped = 0
        self.last_frame_ms = 0.0  # how long the last frame drawn took (render + finish)

    def camera(self, frame: FrameInput) -> Optional[Camera]:
        c = self.state.camera
        if self.follow is not None:
            self.follow.drain()  # keep the transforms current (and the socket's queue short)
        if self.user_camera and c.mode == "fixed":
            self.auto.refresh(frame)
            return self._fixed()
        return self.auto.update(frame)

    def _fixed(self) -> Camera:
        c = self.state.camera
        eye, target = np.asarray(c.eye, np.float64), np.asarray(c.target, np.float64)
        if c.follow and self.follow is not None:
            self.follow.drain()
            o = self.follow.origin(c.follow)
            if o is not None:  # move with the frame's origin since following began
                shift = o - np.asarray(c.follow_anchor if c.follow_anchor is not None else c.target, np.float64)
                eye, target = eye + shift, target + shift
        near, far = self.auto.planes(eye, target, c.up, c.fov_deg)
        return Camera(eye=eye, target=target, up=c.up, fov_deg=c.fov_deg, near=near, far=far)

    def unchanged(self, frame: FrameInput, camera: Camera, renderer: Renderer) -> bool:
        """True when drawing ``frame`` would repeat the last frame: no slot changed, same
        ring window and origin, same camera, same view version, same renderer, no time window."""
        key = (frame.head, frame.size, tuple(np.round(frame.origin, 9)), self.state.version, id(renderer),
               camera.view_proj(16, 9).tobytes(), camera.near, camera.far)
        same = (frame.dirty is not None and not frame.dirty and key == self._drawn_key
                and not self.state.style.time_window_ms > 0)
        self._pending_key = key
        return same

    def drawn(self) -> None:
        self._drawn_key = self._pending_key
        if self.drawn_version != self.state.version:
            self.drawn_version = self.state.version
            self.drawn_ns = time.monotonic_ns()

    def apply(self, msg: dict, window) -> None:
        """Apply one control message (raises ControlError); a camera change reaches the window too."""
        cur = window.camera if window is not None else self.last
        origin = None
        if msg.get("cmd") == "follow" and self.follow is not None and isinstance(msg.get("frame"), str):
            self.follow.drain()
            origin = self.follow.origin(msg["frame"])
        new = control.apply(self.state, msg, current=cur, channels=self.channels, height_px=self.height,
                            sources=self.mask.names, fixed_frame=self.cfg.frames.fixed, follow_origin=origin)
        if new.version == self.state.version:
            return
        if msg.get("cmd") == "fit":
            self.user_camera = False
            self.auto.cfg = dataclasses.replace(self.auto.cfg, mode="auto", position=None, target=None)
        elif new.camera.mode == "fixed" and new.camera != self.state.camera:
            self.user_camera = True
        self.state = new
        self.changed_ns = time.monotonic_ns()
        if window is not None and msg.get("cmd") != "style":
            cam = self.camera_for_window()
            if cam is not None:
                window.controller.camera = cam

    def camera_for_window(self) -> Optional[Camera]:
        c = self.state.camera
        if self.user_camera and c.mode == "fixed":
            return self._fixed()
        return self.auto.camera

    def reply(self, window, frames: int) -> dict:
        d = self.state.to_dict()
        cam = window.camera if window is not None else self.last
        d["camera_drawn"] = None if cam is None else {
            "eye": [float(v) for v in cam.eye], "target": [float(v) for v in cam.target],
            "up": [float(v) for v in cam.up], "fov_deg": float(cam.fov_deg), "near": float(cam.near),
            "far": float(cam.far)}
        f = self.state.camera.follow
        if f:
            known = self.follow is not None and self.follow.origin(f) is not None
            d["follow_status"] = "following" if known else (f"waiting for transforms linking {f!r} to "
                                                            f"{self.cfg.frames.fixed!r}")
        d.update(drawn_version=self.drawn_version, changed_ns=self.changed_ns, drawn_ns=self.drawn_ns,
                 frames=frames, frames_skipped=self.skipped, last_frame_ms=round(self.last_frame_ms, 3),
                 view_block=control.view_block(self.state))
        return d


def frame_from_slab(h, view, now_ns: int, capacity: int) -> FrameInput:
    return FrameInput(
        positions=view.positions, importance=view.importance, t_ingest_ms=view.t_ingest_ms,
        channels=view.channels, head=h.head, size=h.count, capacity=capacity,
        origin=np.asarray(h.origin, np.float64), now_ms=(now_ns - h.epoch_ns) / 1e6,
        channel_ranges=dict(h.channel_ranges), dirty=h.dirty, budget=h.extra.get("budget"),
        seq=h.seq, frame_seed=h.seq,
    )


def write_png(path: str, rgba: np.ndarray) -> None:
    from PIL import Image

    tmp = path + ".tmp"
    Image.fromarray(np.ascontiguousarray(rgba), "RGBA").save(tmp, format="PNG", compress_level=1)
    os.replace(tmp, path)  # readers never see a half-written frame


def _select(cfg, capacity: int, channels: list[str], log) -> Renderer:
    from .select import select_renderer

    renderer, _reasons = select_renderer(cfg.render, capacity, channels, expected_points=cfg.ring.max_points)
    return renderer  # select_renderer logs why each candidate was taken or skipped


def main(ctx: StageContext) -> None:
    cfg = ctx.cfg
    ring = PointRing.attach(ctx.info.ring_name)
    slabs = SlabPair.attach(ctx.info.slab_names)
    capacity = ring_cap = ring.layout.capacity
    channels = [c.name for c in ring.layout.channels]
    maplayer = None
    if getattr(cfg, "map", None) is not None:  # map points as extra slots after the ring's (docs/map.md)
        from .maplayer import MapLayer

        maplayer = MapLayer(cfg, ctx, ring_cap)
        capacity = maplayer.capacity
    ready = ctx.zmq.socket(zmq.PULL)
    ready.setsockopt(zmq.LINGER, 0)
    ready.bind(ctx.endpoints.frames)
    release = ctx.zmq.socket(zmq.PUSH)
    release.setsockopt(zmq.LINGER, 200)
    release.connect(ctx.endpoints.release)
    commands = ctx.zmq.socket(zmq.REP)
    commands.setsockopt(zmq.LINGER, 0)
    commands.bind(ctx.endpoints.render_commands)
    reader = SlabReader(slabs, ready, release)
    poller = zmq.Poller()
    poller.register(ready, zmq.POLLIN)
    poller.register(commands, zmq.POLLIN)
    renderer = ctx.prepared  # a standby's renderer: device created, pipelines warmed up
    if renderer is None:
        renderer = _select(cfg, capacity, channels, ctx.log)
        ctx.log.debug("render tier: %s", renderer.info())  # long; "tier selection" lines say it in short
        _warm_up(renderer, slabs, capacity, ctx.log)
    _announce(release, ctx, renderer)
    view = ViewController(cfg, *cfg.render.size, channels)
    if cfg.frames.fixed and ctx.endpoints.view_transforms:
        tf_in = ctx.zmq.socket(zmq.PULL)
        tf_in.setsockopt(zmq.LINGER, 0)
        tf_in.setsockopt(zmq.RCVHWM, 256)
        tf_in.bind(ctx.endpoints.view_transforms)
        view.follow = FollowFrame(cfg.frames.fixed, tf_in)
    stage = _Stage(renderer=renderer, view=view, capacity=capacity, channels=channels, maplayer=maplayer)
    from .views import ViewHub  # the view server's views (render/views.py)

    stage.hub = ViewHub.open(ctx, cfg, channels, view_cls=ViewController, shared_control=_control,
                             point_dict=point_to_dict)
    if stage.hub is not None:
        poller.register(stage.hub.sock, zmq.POLLIN)
    if ctx.info.restart_count:
        _restore_view(ctx, view, stage)
        renderer = stage.renderer
    window = None
    want_window = cfg.render.window
    if want_window:
        from .window import display_available

        if not display_available():
            ctx.log.warning("render.window is set but there is no display (DISPLAY unset); rendering headless")
            want_window = False
    out = cfg.render.output
    out_dir = ctx.info.out_dir if ctx.info.out_dir else None
    if out_dir:
        os.makedirs(out_dir, exist_ok=True)
    frames = base = int(ctx.info.extra.get("frames_base", 0))  # PNG numbering survives a restart
    ema = None
    c = ctx.counters
    c.extra.update(frames=0, tier=renderer.tier, pngs=0, frame_ms_ema=0.0, tier_info=renderer.info())
    from .rasterswitch import RasterSwitch

    switch = RasterSwitch(renderer, ctx.log)  # compiles the cpu raster beside the stage, if due
    c.extra.update(switch.stats())
    tracing = cfg.tracing.enabled
    t_free = t_idle = time.monotonic_ns()  # when the last frame ended / the last idle message went
    tick_s = 0.0  # the cadence's interval, from its handoffs
    try:
        while ctx.running:
            ctx.beat()
            if maplayer is not None:  # where every view looks, to the map stage (sent when it changed)
                maplayer.publish_stage(stage)
            stage.window, stage.frames = window, frames - base
            _switch_raster(switch, stage, window, ctx)
            _serve_commands(commands, stage, ring, ctx)
            if stage.hub is not None:
                stage.hub.service(stage, ring)
            renderer = stage.renderer
            if window is not None:
                window.process_events()
            # a control message wakes the loop at once (it then shows with the next handoff)
            woke = dict(poller.poll(20 if window is not None else 50))
            got = reader.recv(timeout_ms=0) if ready in woke else None
            if got is not None:  # a message that came with the handoff applies to it
                _serve_commands(commands, stage, ring, ctx)
                renderer = stage.renderer
            if got is None:
                t_idle = _resync_if_idle(release, reader, t_free, t_idle, tick_s)
                continue
            h, slab_view = got
            tick_s = float(h.extra.get("interval_ms") or 0.0) / 1000.0
            drew = False
            frame = None
            try:  # the slab is read only inside this block and goes back in its finally, the one place
                t0 = time.monotonic_ns()
                frame = frame_from_slab(h, slab_view, t0, ring_cap)
                if stage.full_upload:  # a new renderer: everything in the slab is new to it
                    frame.dirty = None
                    stage.full_upload = False
                if maplayer is not None:
                    frame = maplayer.compose(frame)
                camera = window.camera if window is not None else view.camera(frame)
                if window is not None:  # the window's own camera: its planes follow the view too
                    view.auto.refresh(frame)
                    camera.near, camera.far = view.auto.planes(camera.eye, camera.target, camera.up, camera.fov_deg)
                if camera is None:  # nothing to frame yet
                    continue
                if stage.hub is not None and stage.hub.main_rests(window, frame):
                    continue  # views are watched: they draw this handoff (render/views.py)
                if view.unchanged(frame, camera, renderer):  # the same picture again: not drawn
                    view.skipped += 1
                    c.extra["frames_skipped_unchanged"] = view.skipped
                    continue
                frame = view.mask.apply(frame, view.state.hidden_sources)
                try:
                    if want_window and window is None:
                        from .window import PointWindow

                        window = PointWindow(renderer, camera, title=f"pointflow: {cfg.name}",
                                             on_pick=lambda slot, x, y: _print_pick(ring, slot, x, y, maplayer),
                                             on_control=lambda msg: _window_control(view, msg, window, ctx))
                        c.extra["window"] = True
                        ctx.log.info("window open on display %s", os.environ.get("DISPLAY"))
                    if window is not None:
                        if not window.step(frame):
                            ctx.request_stop("window closed")
                            break
                        fs = window.last_stats
                    else:
                        fs = renderer.render(frame, camera)
                    drew = True
                    view.last = camera
                    if maplayer is not None:
                        maplayer.drawn(camera)
                        _warn_apart(ctx, view.auto, maplayer)
                except ValueError as exc:  # a malformed frame (tiers check their input): skip it, counted
                    ctx.log.error("frame %d rejected by the %s tier: %s", h.seq, renderer.tier, exc)
                    c.drop("bad_frame", 1)
                    continue
                except RenderError as exc:
                    from .select import fallback_after

                    ctx.log.error("%s tier failed (%s); falling back", renderer.tier, exc)
                    renderer = fallback_after(renderer, exc, renderer.cfg, capacity, channels)
                    stage.renderer = renderer
                    stage.full_upload = True
                    if window is not None:
                        window.renderer = renderer
                    c.extra["tier"] = renderer.tier
                    c.extra["tier_info"] = renderer.info()
                    switch.follow(renderer)
                    c.extra.update(switch.stats())
                    c.drop("render_error", 1)
                    continue
            finally:
                if stage.hub is not None and frame is not None:
                    stage.hub.handoff(frame, drew, stage)
                reader.release(h.slab)
                t_free = time.monotonic_ns()
                if not drew:  # ready for the next handoff at once
                    _feedback(release, 0.0, h.seq, drawn=False)
            t_up = time.monotonic_ns()
            if (tracing and h.trace_ids or view.drawn_version != view.state.version) and hasattr(renderer, "finish"):
                renderer.finish()  # frame_done means the GPU work is complete
            view.drawn()
            frames += 1
            # the first frame drawn, then every n-th: a picture as soon as there is one
            png = out_dir is not None and (frames % out.every_n_frames == 0 or frames == base + 1)
            if png:
                img = renderer.read_image()
                write_png(os.path.join(out_dir, f"frame_{frames:06d}.png"), img)
                c.extra["pngs"] += 1
                if out.keep_last:
                    old = sorted(glob.glob(os.path.join(out_dir, "frame_*.png")))[:-out.keep_last]
                    for f in old:
                        os.unlink(f)
            t1 = time.monotonic_ns()
            ms = (t1 - t0) / 1e6
            ema = ms if ema is None else 0.85 * ema + 0.15 * ms
            view.last_frame_ms = ms
            c.points_in += h.count
            c.extra["drawn_count"] = h.count  # points in the ring when the last frame was drawn
            if fs.drawn is not None:
                c.points_out += fs.drawn
            c.extra["nonfinite_skipped"] = max(0, int(getattr(renderer, "nonfinite_total", 0)) - view.mask.hidden_draws
                                               - (maplayer.padding_draws if maplayer is not None else 0))
            if maplayer is not None:
                c.extra.update(maplayer.stats())
            if view.mask.hidden_draws:
                c.extra["hidden_skipped"] = view.mask.hidden_draws  # point-draws of hidden sources
            c.extra.update(frames=frames - base, frame_ms_ema=round(ema, 3), last_frame_ms=round(ms, 3),
                           uploaded_bytes=c.extra.get("uploaded_bytes", 0) + fs.uploaded_bytes,
                           **{f"tier_{k}_ms": round(v, 3) for k, v in fs.timings_ms.items()})
            _feedback(release, ms, h.seq)
            t_free = time.monotonic_ns()
            for tid in h.trace_ids:
                ctx.spans.record(tid, "render_upload", t0, t_up, 0)
                ctx.spans.record(tid, "frame_done", t0, t1, 0)
            _gpu_spans(ctx, fs, t0)
    finally:
        if window is not None:
            window.close()
        commands.close(0)
        if maplayer is not None:
            maplayer.close()
        if stage.hub is not None:
            stage.hub.close()
        if view.follow is not None:
            view.follow.sock.close(0)
        if frames and out_dir:
            try:  # the last frame, so a short run always leaves a picture
                write_png(os.path.join(out_dir, "last.png"), renderer.read_image())
            except Exception:  # noqa: BLE001
                ctx.log.exception("writing the last frame")
        renderer.close()
        reader.release()
        slabs.close()
        ring.close()


def _switch_raster(switch, stage: "_Stage", window, ctx) -> None:
    """Between two frames: take the compiled cpu raster once its loops are compiled."""
    new = switch.poll(stage.renderer, stage.capacity, stage.channels)
    if new is not None:
        switch.switched_at_frame = stage.frames
        stage.renderer.close()
        stage.renderer = new
        stage.full_upload = True
        if window is not None:
            window.renderer = new
        ctx.counters.extra.update(tier=new.tier, tier_info=new.info())
    ctx.counters.extra.update(switch.stats())


def _warn_apart(ctx, auto: CameraController, maplayer) -> None:
    """Once: the map and the live points lie far apart (a sensor not placed in the map's frame)."""
    if not auto.apart_m or maplayer.warned_apart:
        return
    maplayer.warned_apart = True
    live = (np.asarray(auto._box[0]) + np.asarray(auto._box[1])) / 2
    mp = (np.asarray(auto.map_box[0]) + np.asarray(auto.map_box[1])) / 2
    ctx.log.warning("the map and the live points lie %.0f apart, in their coordinates' units (live around %s, "
                    "map around %s): the view frames the map; place the sensor in the map's frame with "
                    "frames.fixed and a static transform (docs/map.md#placing-the-live-sensor)", auto.apart_m,
                    np.round(live, 1).tolist(), np.round(mp, 1).tolist())
    ctx.counters.extra["map_apart_m"] = round(float(auto.apart_m), 1)


def _gpu_spans(ctx, fs, t0: int) -> None:
    """GPU timestamp-query durations as spans of their own trace (a ``gpu_compute`` and a
    ``gpu_draw`` slice per frame on the render track). The GPU clock is not the CPU's
    monotonic clock, so the slices are placed at the frame's start; their lengths are the
    GPU's own measurement (which lags the frame by up to two frames)."""
    tm = fs.timings_ms
    if "gpu_compute" not in tm and "gpu_draw" not in tm:
        return
    from ..chunk import new_trace_id

    gid = new_trace_id()
    dc = int(tm.get("gpu_compute", 0.0) * 1e6)
    dd = int(tm.get("gpu_draw", 0.0) * 1e6)
    ctx.spans.record(gid, "gpu_compute", t0, t0 + dc, 0)
    ctx.spans.record(gid, "gpu_draw", t0 + dc, t0 + dc + dd, 0)


def point_to_dict(rec) -> Optional[dict]:
    if rec is None:
        return None
    chans = {k: (np.asarray(v).tolist()) for k, v in rec.channels.items()}
    return {"slot": int(rec.slot), "position": [float(v) for v in rec.position], "channels": chans,
            "t_ingest_ms": float(rec.t_ingest_ms), "generation": int(rec.generation),
            "importance": float(getattr(rec, "importance", 1.0))}


def _print_pick(ring, slot, x, y, maplayer=None) -> None:
    if maplayer is not None:  # a map point, or a live one, named by its source
        p = maplayer.pick_reply(ring, slot, point_to_dict)["point"]
    else:
        rec = ring.get_point(slot) if slot is not None else None
        p = point_to_dict(rec) if rec is not None else None
    print(f"pick ({x:.0f}, {y:.0f}): {p if p is not None else 'nothing within the pick radius'}", flush=True)


@dataclasses.dataclass
class _Stage:
    """What a command may replace: the renderer (a style the tier cannot take in place)."""

    renderer: Renderer
    view: "ViewController"
    capacity: int
    channels: list
    window: Any = None
    hub: Any = None  # the views of a view server (render/views.py)
    frames: int = 0
    maplayer: Any = None  # render/maplayer.py with a ``map:`` block
    #: The next frame uploads the whole slab (a renderer built since the last frame).
    full_upload: bool = False


def _serve_commands(sock, stage: _Stage, ring, ctx) -> None:
    """Answer pending REQ/REP requests: ``pick`` (resolved through the ring, generation-checked),
    ``save`` (write the current frame as PNG or JPEG) and the view control messages of
    :mod:`pointflow.render.control` (a bad one is answered with its error, counted
    ``bad_control``; the view stays as it was)."""
    while sock.poll(0, zmq.POLLIN):
        try:
            req = json.loads(sock.recv())
            cmd = req.get("cmd") if isinstance(req, dict) else None
            if cmd in ("pick", "save") and stage.hub is not None:
                stage.hub.restore_main(stage)  # a view's picture may be in the target
            renderer = stage.renderer
            if cmd == "pick":
                slot = renderer.pick(float(req["x"]), float(req["y"]), float(req.get("pixel_ratio", 1.0)))
                if stage.maplayer is not None:  # a map point, or a live one with its source named
                    rep = stage.maplayer.pick_reply(ring, slot, point_to_dict)
                else:
                    rep = {"point": point_to_dict(ring.get_point(slot)) if slot is not None else None}
            elif cmd == "save":
                path = str(req["path"])
                os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
                from .imagefile import write_image  # PNG or JPEG, by its suffix

                write_image(path, renderer.read_image())
                rep = {"path": path}
            else:  # the view control messages; an unknown one is refused there, naming them
                rep = _control(req, stage, ctx)
        except ControlError as exc:
            ctx.counters.drop("bad_control", 1)
            ctx.log.warning("render control message refused: %s", exc)
            rep = {"error": str(exc), "key": exc.key}
        except Exception as exc:  # noqa: BLE001 - a bad request must not kill the stage
            ctx.log.warning("render command failed: %s", exc)
            rep = {"error": f"{type(exc).__name__}: {exc}"}
        sock.send_string(json.dumps(rep))


def _view_file(ctx) -> Optional[str]:
    d = getattr(ctx.info, "run_dir", None)
    return os.path.join(d, "view-state.json") if d else None


def _keep_view(ctx, view: "ViewController") -> None:
    """Write the view where a restarted render stage finds it (the private run directory)."""
    path = _view_file(ctx)
    if not path:
        return
    try:
        tmp = path + ".tmp"
        with open(tmp, "w") as f:
            json.dump({"state": view.state.to_dict(), "user_camera": view.user_camera}, f)
        os.replace(tmp, path)
    except OSError as exc:  # the view still works; only a restart would forget it
        ctx.log.warning("could not keep the view state for a restart: %s", exc)


def _restore_view(ctx, view: "ViewController", stage: "_Stage") -> None:
    """A restarted render stage takes up the view its predecessor had (camera, style, hidden)."""
    path = _view_file(ctx)
    if not path or not os.path.exists(path):
        return
    try:
        with open(path) as f:
            d = json.load(f)
        s = d["state"]
        state = ViewState(camera=control.CameraState(**s["camera"]), style=control.StyleState(**s["style"]),
                          hidden_sources=list(s.get("hidden_sources", [])), version=int(s["version"]))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        ctx.log.warning("the kept view state is unreadable (%s); starting from the config", exc)
        return
    view.state, view.user_camera = state, bool(d.get("user_camera"))
    r = stage.renderer
    new_cfg = style_render_config(r.cfg, state.style)
    if not r.restyle(new_cfg):
        nr = _same_tier(r, new_cfg, stage)
        r.close()
        stage.renderer = nr
        stage.full_upload = True
    ctx.log.info("view state of the previous render stage taken up (version %d)", state.version)


def _same_tier(r: Renderer, new_cfg, stage: _Stage) -> Renderer:
    """A new renderer of ``r``'s tier with another style; a compile still due carries over
    (the raster switch reads ``compiled_pending``)."""
    nr = type(r)(new_cfg, stage.capacity, stage.channels)
    if getattr(r, "compiled_pending", None) is not None:
        nr.compiled_pending = r.compiled_pending  # type: ignore[attr-defined]
    return nr


def _control(req: dict, stage: _Stage, ctx) -> dict:
    """Apply a view control message; a new style goes to the renderer (in place, or a new
    renderer of the same tier when the tier caches it)."""
    view = stage.view
    old = view.state
    view.apply(req, stage.window)
    if view.state.style != old.style:
        r = stage.renderer
        new_cfg = style_render_config(r.cfg, view.state.style)
        if not r.restyle(new_cfg):
            try:
                nr = _same_tier(r, new_cfg, stage)
            except Exception as exc:  # noqa: BLE001 - keep drawing with the old style
                view.state = old
                raise ControlError("style", f"the {r.tier} tier could not take the new style: {exc}") from None
            r.close()
            stage.renderer = nr
            stage.full_upload = True
            if stage.window is not None:
                stage.window.renderer = nr
            ctx.counters.extra["tier_info"] = nr.info()
            ctx.log.info("new %s renderer for the style %s", nr.tier, dataclasses.asdict(view.state.style))
    if view.state.version != old.version:
        ctx.counters.extra["view_version"] = view.state.version
        _keep_view(ctx, view)
    return view.reply(stage.window, stage.frames)


def prepare(cfg, info, log) -> Optional[Renderer]:
    """A standby renderer's head start (:data:`KIND`'s ``prepare``):
    create the device and draw the warm-up frame while the renderer it may replace still
    runs. On an idle 2-core machine with lavapipe this is 1.2-1.4 s of device creation and
    0.5-1.2 s of warm-up that a restart no longer waits for."""
    ring = PointRing.attach(info.ring_name)
    slabs = SlabPair.attach(info.slab_names)
    try:
        from ..map.config import map_slots

        capacity = ring.layout.capacity + map_slots(cfg)  # a map's slots follow the ring's
        renderer = _select(cfg, capacity, [c.name for c in ring.layout.channels], log)
        log.debug("standby render tier: %s", renderer.info())
        _warm_up(renderer, slabs, capacity, log)
        return renderer
    finally:
        slabs.close()
        ring.close()


#: Started first (it binds what the cadence pushes handoffs to), stopped last.
KIND = register_stage_kind(StageKind(name="render", main="pointflow.render.process:main",
                                     prepare="pointflow.render.process:prepare", start_order=10, stop_wave=2,
                                     standby=True, counters=("frames", "pngs", "uploaded_bytes")))


def _warm_up(renderer: Renderer, slabs: SlabPair, capacity: int, log) -> None:
    """Draw one tiny frame of zeros before reporting in. A tier's first frame compiles its
    pipelines (lavapipe: 0.5 s of 0.7 s on an idle 2-core machine, more under load); done
    here, a restarted renderer's first real frame (a full upload after its hello) costs no
    more than any full frame, so frames resume sooner after a render restart."""
    t0 = time.monotonic()
    try:
        v = slabs.slab_view(0)
        n = min(1024, capacity)
        z = lambda a: np.zeros((capacity,) + a.shape[1:], a.dtype)  # noqa: E731 - capacity may exceed the slab's
        chans = {k: z(a) for k, a in v.channels.items()}
        ranges = {k: (0.0, 1.0) for k, a in chans.items() if a.ndim == 1 and a.dtype.kind == "f"}
        frame = FrameInput(positions=z(v.positions), importance=z(v.importance) + 1,
                           t_ingest_ms=z(v.t_ingest_ms), channels=chans, head=0, size=n,
                           capacity=capacity, origin=np.zeros(3), now_ms=0.0, channel_ranges=ranges,
                           dirty=[(0, n)], seq=0)
        renderer.render(frame, Camera.fit(np.full(3, -1.0), np.ones(3), aspect=16 / 9))
        if hasattr(renderer, "finish"):
            renderer.finish()
    except Exception as exc:  # noqa: BLE001 - only a head start; the real frames will tell
        log.debug("warm-up frame failed (%s); the first frame compiles instead", exc)
        return
    log.info("warm-up frame drawn in %.0f ms", (time.monotonic() - t0) * 1000)


def _announce(sock, ctx, renderer: Renderer) -> None:
    """Tell the cadence a (new) renderer holds no slab, and what GPU it drives (the policy
    engine caps the budget by the adapter's storage limits and detects the tier from it)."""
    from ..cadence.messages import encode_hello

    gpu = None
    adapter = getattr(renderer, "adapter", None)
    if adapter is not None:
        try:
            from ..cadence.policy import gpu_info_from_adapter

            gpu = gpu_info_from_adapter(adapter)
        except Exception as exc:  # noqa: BLE001 - the policy then works from CPU and memory alone
            ctx.log.warning("could not describe the GPU adapter for the policy engine: %s", exc)
    try:
        sock.send_multipart(encode_hello(os.getpid(), ctx.info.restart_count, gpu=gpu), zmq.NOBLOCK)
    except zmq.Again:
        pass


#: A renderer that holds no slab and got no handoff for this long (or 4 cadence ticks, if
#: longer) tells the cadence so; a healthy cadence hands the next snapshot over within a tick.
IDLE_RESYNC_S = 0.5


def _resync_if_idle(sock, reader: SlabReader, t_free: int, t_idle: int, tick_s: float) -> int:
    """Send ``idle`` (pointflow.cadence.messages) when no handoff came for a while: a
    cadence that froze and was replaced never read the releases queued to it and would
    otherwise wait for them forever. Returns when an idle message last went."""
    now = time.monotonic_ns()
    since = max(t_free, reader.t_last_ns, t_idle)
    limit = max(IDLE_RESYNC_S, 4 * tick_s)
    if reader.held is not None or (now - since) / 1e9 < limit:
        return t_idle
    from ..cadence.messages import encode_idle

    try:
        sock.send_multipart(encode_idle(reader.last_seq, (now - max(t_free, reader.t_last_ns)) / 1e6), zmq.NOBLOCK)
    except zmq.Again:
        pass
    return now


def _feedback(sock, frame_ms: float, seq: int, drawn: bool = True) -> None:
    """Frame done (the cadence hands over the next snapshot now) and its time (the
    adaptive interval)."""
    try:
        from ..cadence.messages import encode_frame_time

        sock.send_multipart(encode_frame_time(frame_ms, seq, drawn), zmq.NOBLOCK)
    except (ImportError, zmq.Again):
        pass
