"""A view's controller: its camera (framed on the data, or the user's, or following a frame),
the sources it hides, and whether a frame would repeat the last one drawn.

The main view and every view of the hub (hub.py) each hold one :class:`ViewController`;
their control messages are checked once, by :func:`pointflow.render.view.protocol.apply`.
"""
from __future__ import annotations

import dataclasses
import json
import time
from typing import Optional

import numpy as np
import zmq

from ...arrays import column_max, column_min, finite_rows
from ..base import FrameInput, Renderer
from ..camera import Camera, clip_planes, scene_box
from . import protocol
from .protocol import ViewState

__all__ = ["CameraController", "SourceMask", "FollowFrame", "ViewController"]

#: At most this share of the render loop's time goes to the planes' box (the min/max of every
#: live position: about 1 ms per 300k points here), however often the ring moves.
CLIP_SHARE = 0.05


class CameraController:
    """Frames the scene automatically (``camera.mode: auto``/``orbit``) or uses the fixed
    camera from the config. The framing box comes from a strided sample of the occupied slots,
    checked about once a second (not every frame); the camera refits when it changed by more
    than 10%, so it follows a growing map or a moving sensor without jitter. The near and far
    planes hold every live point's box, taken again whenever the ring moved (cost-bounded). With a map, the live
    points' box and the map's are kept apart: the camera frames the map when the two lie far
    apart (``apart_m``), and near and far planes follow what lies in front of the camera."""

    def __init__(self, ctx_cfg, width: int, height: int):
        self.cfg = ctx_cfg.render.camera
        self.aspect = width / max(height, 1)
        self.camera: Optional[Camera] = None
        self._last_fit = 0.0
        self._box = None
        self._clip = None  # the live points' min/max box (with a margin): what the planes must hold
        self._clip_t, self._clip_cost, self._clip_sig, self._seen_sig = -1e9, 0.0, None, None
        self.map_box = None
        self.apart_m = 0.0  # how far apart map and live points are (0: not apart)
        self._t0 = time.monotonic()
        if self.cfg.mode == "fixed":
            self.camera = Camera(eye=self.cfg.position, target=self.cfg.target, up=self.cfg.up,
                                 fov_deg=self.cfg.fov_deg, near=self.cfg.near, far=self.cfg.far)

    @staticmethod
    def _fit_box(frame: FrameInput):
        """1st-99th percentile box of a strided sample of the occupied live slots (world
        coords): what the camera frames (about once a second)."""
        p = CameraController._sample(frame)
        if p is None:
            return None
        lo, hi = np.percentile(p, [1, 99], axis=0)
        return lo + frame.origin, hi + frame.origin

    @staticmethod
    def _sample(frame: FrameInput, limit: int = 50_000):
        slots = frame.occupied_slots()
        if frame.live_slots is not None:
            slots = slots[slots < frame.live_slots]
        step = max(1, slots.size // limit)
        p = frame.positions[slots[::step]].astype(np.float64)
        p = p[finite_rows(p)]
        return p if p.size else None

    @staticmethod
    def _clip_box(frame: FrameInput):
        """The min/max box of every occupied live slot, widened by a tenth (and 0.5 m): what
        the near and far planes must hold. None without a finite position."""
        ext = CameraController._extent(frame)
        if ext is None:  # some position is not finite (or nothing is there): those rows are left out
            p = CameraController._sample(frame, limit=1 << 62)
            if p is None:
                return None
            ext = column_min(p), column_max(p)
        mlo, mhi = ext
        pad = 0.1 * (mhi - mlo) + 0.5
        return mlo - pad + frame.origin, mhi + pad + frame.origin

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
        """Keep the boxes current. The framing box about once a second (refit only on a >10%
        change: no jitter). The planes' box whenever the ring moved (its head or size) since
        it was taken: at once when the ring stopped moving (the next look, a handoff or a draw,
        finds it where it was), while it moves with at most :data:`CLIP_SHARE` of the time spent
        on it (a big ring waits longer between reductions), and at least once a second. Points
        that came after it must not stay outside near and far (a still scene half drawn, seen
        in a test: the box was taken once a second)."""
        now = time.monotonic()
        if frame.map_box is not None:
            self.map_box = frame.map_box
        if frame.size and (self._box is None or now - self._last_fit > 1.0):
            self._last_fit = now
            box = self._fit_box(frame)
            if box is not None and (self._box is None or self._moved(box)):
                self._box = box
        sig = (int(frame.head), int(frame.size), int(frame.capacity), tuple(np.round(frame.origin, 9)))
        since, settled = now - self._clip_t, sig == self._seen_sig  # the ring did not move since the last look
        self._seen_sig = sig
        if frame.size and (since > 1.0 or sig != self._clip_sig
                           and (settled or since > self._clip_cost / CLIP_SHARE)):
            t0 = time.perf_counter()
            self._clip = self._clip_box(frame)
            self._clip_cost = time.perf_counter() - t0
            self._clip_t, self._clip_sig = now, sig
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
        src = frame.channels.get(protocol.SOURCE_CHANNEL)
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
        from ...frames.buffer import TransformBuffer

        self.fixed = fixed
        self.sock = sock
        self.buf = TransformBuffer()
        self.bad = 0

    def drain(self) -> None:
        from ...frames import message as tfmsg
        from ...frames.buffer import FrameError

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


class ViewController:
    """The render stage's view: the control state (:mod:`pointflow.render.view.protocol`), the
    camera it gives each frame, and whether a frame would look like the last one drawn
    (then it is not drawn: an idle pipeline costs the render stage next to no CPU)."""

    def __init__(self, cfg, width: int, height: int, channels: list[str]):
        self.cfg = cfg
        self.auto = CameraController(cfg, width, height)
        self.state = ViewState.from_render_config(cfg.render)
        if isinstance(cfg.view, dict) and cfg.view.get("hidden_sources"):
            self.state.hidden_sources = list(cfg.view["hidden_sources"])
        self.mask = SourceMask([s.name for s in cfg.sources])
        self.follow: Optional[FollowFrame] = None  # set by the render stage with frames.fixed
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
        new = protocol.apply(self.state, msg, current=cur, channels=self.channels, height_px=self.height,
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
                 view_block=protocol.view_block(self.state))
        return d
