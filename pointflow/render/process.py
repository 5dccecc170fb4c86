"""The render stage: receive slab handoffs, draw them with the chosen tier, write PNGs.

Per handoff: build a :class:`FrameInput` over the slab (no copy), update the camera,
``renderer.render()``, give the slab back at once (tiers copy what they keep), record
spans, and every ``output.every_n_frames`` frames read the image back and save a PNG.
"""
from __future__ import annotations

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
from ..stage.kinds import StageKind, register_stage_kind
from ..stage.context import StageContext
from .base import FrameInput, RenderError, Renderer
from . import handoffs
from .camera import Camera
from .view import mainview
from .view.controller import CameraController, FollowFrame, ViewController
from .view.hub import ViewHub
from .view.protocol import ControlError, point_to_dict


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
    """The render stage's loop (:data:`KIND`'s ``main``)."""
    stage = _Stage(ctx)
    try:
        while ctx.running and stage.turn():
            pass
    finally:
        stage.close()


class _Stage:
    """The render stage: its sockets, its renderer (what a command may replace: a style the
    tier cannot take in place, a fallback, the compiled raster), the main view and the hub's
    views, and the steps of one loop turn."""

    def __init__(self, ctx: StageContext):
        self.ctx = ctx
        cfg = self.cfg = ctx.cfg
        self.ring = PointRing.attach(ctx.info.ring_name)
        self.slabs = SlabPair.attach(ctx.info.slab_names)
        self.capacity = self.ring_cap = self.ring.layout.capacity
        self.channels = [c.name for c in self.ring.layout.channels]
        self.maplayer = None  # render/maplayer.py with a ``map:`` block
        if getattr(cfg, "map", None) is not None:  # map points as extra slots after the ring's (docs/map.md)
            from .maplayer import MapLayer

            self.maplayer = MapLayer(cfg, ctx, self.ring_cap)
            self.capacity = self.maplayer.capacity
        self._sockets()
        renderer = ctx.prepared  # a standby's renderer: device created, pipelines warmed up
        if renderer is None:
            renderer = _select(cfg, self.capacity, self.channels, ctx.log)
            ctx.log.debug("render tier: %s", renderer.info())  # long; "tier selection" lines say it in short
            _warm_up(renderer, self.slabs, self.capacity, ctx.log)
        self.renderer: Renderer = renderer
        handoffs.announce(self.release, ctx, renderer)
        self.window: Any = None
        self.frames = 0  # frames drawn by this process (the hub and the raster switch read it)
        #: The next frame uploads the whole slab (a renderer built since the last frame).
        self.full_upload = False
        self._views()
        self.want_window = cfg.render.window
        if self.want_window:
            from .window import display_available

            if not display_available():
                ctx.log.warning("render.window is set but there is no display (DISPLAY unset); rendering headless")
                self.want_window = False
        self.out_dir = ctx.info.out_dir if ctx.info.out_dir else None
        if self.out_dir:
            os.makedirs(self.out_dir, exist_ok=True)
        self.total = self.base = int(ctx.info.extra.get("frames_base", 0))  # PNG numbering survives a restart
        self.ema: Optional[float] = None
        ctx.counters.extra.update(frames=0, tier=self.renderer.tier, pngs=0, frame_ms_ema=0.0,
                                  tier_info=self.renderer.info())
        from .rasterswitch import RasterSwitch

        self.switch = RasterSwitch(self.renderer, ctx.log)  # compiles the cpu raster beside the stage, if due
        ctx.counters.extra.update(self.switch.stats())
        self.t_free = self.t_idle = time.monotonic_ns()  # when the last frame ended / the last idle message went
        self.tick_s = 0.0  # the cadence's interval, from its handoffs

    def _sockets(self) -> None:
        ctx = self.ctx
        self.ready = ctx.zmq.socket(zmq.PULL)
        self.ready.setsockopt(zmq.LINGER, 0)
        self.ready.bind(ctx.endpoints.frames)
        self.release = ctx.zmq.socket(zmq.PUSH)
        self.release.setsockopt(zmq.LINGER, 200)
        self.release.connect(ctx.endpoints.release)
        self.commands = ctx.zmq.socket(zmq.REP)
        self.commands.setsockopt(zmq.LINGER, 0)
        self.commands.bind(ctx.endpoints.render_commands)
        self.reader = SlabReader(self.slabs, self.ready, self.release)
        self.poller = zmq.Poller()
        self.poller.register(self.ready, zmq.POLLIN)
        self.poller.register(self.commands, zmq.POLLIN)

    def _views(self) -> None:
        """The main view (following a frame with ``frames.fixed``), the hub's views, and the
        view a restarted render stage takes up."""
        ctx, cfg = self.ctx, self.cfg
        self.view = ViewController(cfg, *cfg.render.size, self.channels)
        if cfg.frames.fixed and ctx.endpoints.view_transforms:
            tf_in = ctx.zmq.socket(zmq.PULL)
            tf_in.setsockopt(zmq.LINGER, 0)
            tf_in.setsockopt(zmq.RCVHWM, 256)
            tf_in.bind(ctx.endpoints.view_transforms)
            self.view.follow = FollowFrame(cfg.frames.fixed, tf_in)
        self.hub = ViewHub.open(ctx, cfg, self.channels)  # the view server's and notebooks' views
        if self.hub is not None:
            self.poller.register(self.hub.sock, zmq.POLLIN)
        if ctx.info.restart_count:
            mainview.restore(ctx, self.view, self)

    # ------------------------------------------------------------------ one loop turn
    def turn(self) -> bool:
        """One turn: commands, views, then a handoff if one came. False: stop (window closed)."""
        ctx = self.ctx
        ctx.beat()
        if self.maplayer is not None:  # where every view looks, to the map stage (sent when it changed)
            self.maplayer.publish_stage(self)
        self.frames = self.total - self.base
        _switch_raster(self.switch, self, ctx)
        _serve_commands(self.commands, self, self.ring, ctx)
        if self.hub is not None:
            self.hub.service(self, self.ring)
        if self.window is not None:
            self.window.process_events()
        # a control message wakes the loop at once (it then shows with the next handoff)
        woke = dict(self.poller.poll(20 if self.window is not None else 50))
        got = self.reader.recv(timeout_ms=0) if self.ready in woke else None
        if got is None:
            self.t_idle = handoffs.resync_if_idle(self.release, self.reader, self.t_free, self.t_idle, self.tick_s)
            return True
        _serve_commands(self.commands, self, self.ring, ctx)  # a message that came with the handoff applies to it
        h, slab_view = got
        self.tick_s = float(h.extra.get("interval_ms") or 0.0) / 1000.0
        drew, frame, fs, stop = False, None, None, False
        t0 = time.monotonic_ns()
        try:  # the slab is read only inside this block and goes back in its finally, the one place
            frame = frame_from_slab(h, slab_view, t0, self.ring_cap)
            if self.full_upload:  # a new renderer: everything in the slab is new to it
                frame.dirty = None
                self.full_upload = False
            if self.maplayer is not None:
                frame = self.maplayer.compose(frame)
            fs, stop = self._draw(frame, h.seq)
            drew = fs is not None
        finally:
            if self.hub is not None and frame is not None:
                self.hub.handoff(frame, drew, self)
            self.reader.release(h.slab)
            self.t_free = time.monotonic_ns()
            if not drew:  # ready for the next handoff at once
                handoffs.feedback(self.release, 0.0, h.seq, drawn=False)
        if stop:
            return False
        if drew:
            self._drawn(h, fs, t0)
        return True

    def _camera(self, frame: FrameInput) -> Optional[Camera]:
        view, window = self.view, self.window
        camera = window.camera if window is not None else view.camera(frame)
        if window is not None:  # the window's own camera: its planes follow the view too
            view.auto.refresh(frame)
            camera.near, camera.far = view.auto.planes(camera.eye, camera.target, camera.up, camera.fov_deg)
        return camera

    def _draw(self, frame: FrameInput, seq: int) -> tuple[Any, bool]:
        """Draw the main view's frame unless it would repeat the last or the views draw it.
        Returns (its FrameStats or None, whether the stage stops: the window was closed)."""
        ctx, view, c = self.ctx, self.view, self.ctx.counters
        camera = self._camera(frame)
        if camera is None:  # nothing to frame yet
            return None, False
        if self.hub is not None and self.hub.main_rests(self.window, frame):
            return None, False  # views are watched: they draw this handoff (render/view/hub.py)
        if view.unchanged(frame, camera, self.renderer):  # the same picture again: not drawn
            view.skipped += 1
            c.extra["frames_skipped_unchanged"] = view.skipped
            return None, False
        frame = view.mask.apply(frame, view.state.hidden_sources)
        try:
            if self.want_window and self.window is None:
                self._open_window(camera)
            if self.window is not None:
                if not self.window.step(frame):
                    ctx.request_stop("window closed")
                    return None, True
                fs = self.window.last_stats
            else:
                fs = self.renderer.render(frame, camera)
            view.last = camera
            if self.maplayer is not None:
                self.maplayer.drawn(camera)
                _warn_apart(ctx, view.auto, self.maplayer)
            return fs, False
        except ValueError as exc:  # a malformed frame (tiers check their input): skip it, counted
            ctx.log.error("frame %d rejected by the %s tier: %s", seq, self.renderer.tier, exc)
            c.drop("bad_frame", 1)
        except RenderError as exc:
            self._fall_back(exc)
        return None, False

    def _open_window(self, camera: Camera) -> None:
        from .window import PointWindow

        ring, maplayer = self.ring, self.maplayer
        self.window = PointWindow(self.renderer, camera, title=f"pointflow: {self.cfg.name}",
                                  on_pick=lambda slot, x, y: _print_pick(ring, slot, x, y, maplayer),
                                  on_control=lambda msg: mainview.window_control(msg, self, self.ctx))
        self.ctx.counters.extra["window"] = True
        self.ctx.log.info("window open on display %s", os.environ.get("DISPLAY"))

    def _fall_back(self, exc: RenderError) -> None:
        from .select import fallback_after

        c = self.ctx.counters
        r = self.renderer
        self.ctx.log.error("%s tier failed (%s); falling back", r.tier, exc)
        self.renderer = fallback_after(r, exc, r.cfg, self.capacity, self.channels)
        self.full_upload = True
        if self.window is not None:
            self.window.renderer = self.renderer
        c.extra["tier"] = self.renderer.tier
        c.extra["tier_info"] = self.renderer.info()
        self.switch.follow(self.renderer)
        c.extra.update(self.switch.stats())
        c.drop("render_error", 1)

    def _drawn(self, h, fs, t0: int) -> None:
        """After a frame: finish it when someone waits for it, a PNG when due, counters, spans,
        and the frame time to the cadence."""
        ctx, c, view, renderer = self.ctx, self.ctx.counters, self.view, self.renderer
        t_up = time.monotonic_ns()
        if (self.cfg.tracing.enabled and h.trace_ids or view.drawn_version != view.state.version) \
                and hasattr(renderer, "finish"):
            renderer.finish()  # frame_done means the GPU work is complete
        view.drawn()
        self.total += 1
        self._png()
        t1 = time.monotonic_ns()
        ms = (t1 - t0) / 1e6
        self.ema = ms if self.ema is None else 0.85 * self.ema + 0.15 * ms
        view.last_frame_ms = ms
        c.points_in += h.count
        c.extra["drawn_count"] = h.count  # points in the ring when the last frame was drawn
        if fs.drawn is not None:
            c.points_out += fs.drawn
        ml = self.maplayer
        c.extra["nonfinite_skipped"] = max(0, int(getattr(renderer, "nonfinite_total", 0)) - view.mask.hidden_draws
                                           - (ml.padding_draws if ml is not None else 0))
        if ml is not None:
            c.extra.update(ml.stats())
        if view.mask.hidden_draws:
            c.extra["hidden_skipped"] = view.mask.hidden_draws  # point-draws of hidden sources
        c.extra.update(frames=self.total - self.base, frame_ms_ema=round(self.ema, 3), last_frame_ms=round(ms, 3),
                       uploaded_bytes=c.extra.get("uploaded_bytes", 0) + fs.uploaded_bytes,
                       **{f"tier_{k}_ms": round(v, 3) for k, v in fs.timings_ms.items()})
        handoffs.feedback(self.release, ms, h.seq)
        self.t_free = time.monotonic_ns()
        for tid in h.trace_ids:
            ctx.spans.record(tid, "render_upload", t0, t_up, 0)
            ctx.spans.record(tid, "frame_done", t0, t1, 0)
        _gpu_spans(ctx, fs, t0)

    def _png(self) -> None:
        """The first frame drawn, then every n-th: a picture as soon as there is one."""
        out = self.cfg.render.output
        n = self.total
        if self.out_dir is None or not (n % out.every_n_frames == 0 or n == self.base + 1):
            return
        write_png(os.path.join(self.out_dir, f"frame_{n:06d}.png"), self.renderer.read_image())
        self.ctx.counters.extra["pngs"] += 1
        if out.keep_last:
            for f in sorted(glob.glob(os.path.join(self.out_dir, "frame_*.png")))[:-out.keep_last]:
                os.unlink(f)

    def close(self) -> None:
        if self.window is not None:
            self.window.close()
            # the window's control callback holds this stage: a cycle that would keep the
            # sockets below open until a garbage collection, and the stage context's zmq
            # term() waiting on them (a window's render stage was killed on every stop)
            self.window = None
        self.commands.close(0)
        if self.maplayer is not None:
            self.maplayer.close()
        if self.hub is not None:
            self.hub.close()
        if self.view.follow is not None:
            self.view.follow.sock.close(0)
        if self.total and self.out_dir:
            try:  # the last frame, so a short run always leaves a picture
                write_png(os.path.join(self.out_dir, "last.png"), self.renderer.read_image())
            except Exception:  # noqa: BLE001
                self.ctx.log.exception("writing the last frame")
        self.renderer.close()
        self.reader.release()
        self.ready.close(0)
        self.release.close()  # (its linger lets the release just sent go out)
        self.slabs.close()
        self.ring.close()


def _switch_raster(switch, stage: _Stage, ctx) -> None:
    """Between two frames: take the compiled cpu raster once its loops are compiled."""
    new = switch.poll(stage.renderer, stage.capacity, stage.channels)
    if new is not None:
        switch.switched_at_frame = stage.frames
        stage.renderer.close()
        stage.renderer = new
        stage.full_upload = True
        if stage.window is not None:
            stage.window.renderer = new
        ctx.counters.extra.update(tier=new.tier, tier_info=new.info())
    ctx.counters.extra.update(switch.stats())


def _warn_apart(ctx, auto: CameraController, maplayer) -> None:
    """Once: the map and the live points lie far apart (a sensor not placed in the map's frame)."""
    if not auto.apart_m or maplayer.warned_apart:
        return
    maplayer.warned_apart = True
    live = (np.asarray(auto._box[0]) + np.asarray(auto._box[1])) / 2
    mp = (np.asarray(auto.map_box[0]) + np.asarray(auto.map_box[1])) / 2
    unit = (maplayer.units or {}).get("xy")
    ctx.log.warning("the map and the live points lie %.0f %s apart (live around %s, "
                    "map around %s): the view frames the map; place the sensor in the map's frame with "
                    "frames.fixed and a static transform (docs/map.md#placing-the-live-sensor)", auto.apart_m,
                    f"{unit} (the map's CRS)" if unit else "units", np.round(live, 1).tolist(), np.round(mp, 1).tolist())
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


def _print_pick(ring, slot, x, y, maplayer=None) -> None:
    if maplayer is not None:  # a map point, or a live one, named by its source
        p = maplayer.pick_reply(ring, slot, point_to_dict)["point"]
    else:
        rec = ring.get_point(slot) if slot is not None else None
        p = point_to_dict(rec) if rec is not None else None
    print(f"pick ({x:.0f}, {y:.0f}): {p if p is not None else 'nothing within the pick radius'}", flush=True)


def _serve_commands(sock, stage: _Stage, ring, ctx) -> None:
    """Answer pending REQ/REP requests: ``pick`` (resolved through the ring, generation-checked),
    ``save`` (write the current frame as PNG or JPEG) and the view control messages of
    :mod:`pointflow.render.view.protocol` (a bad one is answered with its error, counted
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
                rep = mainview.steer(req, stage, ctx)
        except ControlError as exc:
            ctx.counters.drop("bad_control", 1)  # (the caller gets the error and raises it: not logged twice)
            ctx.log.debug("render control message refused: %s", exc)
            rep = {"error": str(exc), "key": exc.key, "message": exc.message}
        except Exception as exc:  # noqa: BLE001 - a bad request must not kill the stage
            ctx.log.warning("render command failed: %s", exc)
            rep = {"error": f"{type(exc).__name__}: {exc}"}
        sock.send_string(json.dumps(rep))


def prepare(cfg, info, log) -> Optional[Renderer]:
    """A standby renderer's head start (:data:`KIND`'s ``prepare``):
    create the device and draw the warm-up frame while the renderer it may replace still
    runs. On an idle 2-core machine with lavapipe this is 1.2-1.4 s of device creation and
    0.5-1.2 s of warm-up that a restart no longer waits for."""
    ring = PointRing.attach(info.ring_name)
    slabs = SlabPair.attach(info.slab_names)
    try:
        from .mapregion import map_slots

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
