"""Optional on-screen window (rendercanvas + glfw): orbit/pan/zoom, click-to-pick, stats in the title.

Headless is the default; the window is an extra (``pip install pointflow[window]``) and
needs a display (``DISPLAY``/Wayland, or Xvfb). The renderer keeps drawing into its own
texture; the window shows the frame through rendercanvas' bitmap context, so it works with
any tier that implements ``read_image()`` (wgpu, gl, cpu) at the price of one readback per
shown frame. Mouse: left drag orbits, right (or shift+left) drag pans, wheel zooms, a click
without drag picks the point under the cursor (``on_pick(slot)``; default: print it).
"""
from __future__ import annotations

import os
import time
from typing import Any, Callable, Optional

import numpy as np

from .base import FrameInput, FrameStats, Renderer
from .camera import Camera, OrbitController  # noqa: F401 - OrbitController lives with the camera

CLICK_TOLERANCE_PX = 3.0


def display_available() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


class PointWindow:
    """A window that shows a renderer's frames and drives its camera.

    ``step(frame)`` renders ``frame`` with the window's camera, presents it and handles the
    pending input; it returns False once the user closed the window. Picks run on the
    last rendered frame (``renderer.pick(x, y, pixel_ratio)``)."""

    def __init__(self, renderer: Renderer, camera: Camera, *, title: str = "pointflow",
                 on_pick: Optional[Callable[[Optional[int], float, float], Any]] = None,
                 on_control: Optional[Callable[[dict], Any]] = None):
        if not display_available():
            raise RuntimeError("no display (DISPLAY/WAYLAND_DISPLAY unset); run headless or under Xvfb")
        from rendercanvas.glfw import GlfwRenderCanvas
        self.renderer = renderer
        self.controller = OrbitController(camera)
        self.title = title
        self.on_pick = on_pick or (lambda slot, x, y: print(f"pick ({x:.0f}, {y:.0f}) -> slot {slot}"))
        #: With it, mouse and wheel become view control messages (render/view/protocol.py), the
        #: set Python and other views use; the render stage applies them and sets the camera.
        self.on_control = on_control
        w, h = renderer.width, renderer.height
        self.canvas = GlfwRenderCanvas(size=(w, h), title=title, update_mode="manual")
        self._ctx = self.canvas.get_bitmap_context()
        self._image: Optional[np.ndarray] = None
        self.canvas.request_draw(self._draw)
        self.canvas.add_event_handler(self._on_event, "pointer_down", "pointer_move", "pointer_up", "wheel")
        self._down: Optional[tuple[float, float, int, bool]] = None
        self._last_xy = (0.0, 0.0)
        self._dirty = True
        self.frames = 0
        self._t_last = time.perf_counter()
        self._fps = 0.0
        self.last_stats: Optional[FrameStats] = None
        self.picks: list[Optional[int]] = []
        self.last_title = title

    @property
    def camera(self) -> Camera:
        return self.controller.camera

    def _draw(self) -> None:
        if self._image is not None:
            self._ctx.set_bitmap(self._image)

    def _on_event(self, e: dict) -> None:
        et = e["event_type"]
        if et == "wheel":
            self._turn("zoom", e.get("dy", 0.0), 0.0)
        elif et == "pointer_down":
            shift = "Shift" in e.get("modifiers", ())
            self._down = (e["x"], e["y"], e.get("button", 1), shift)
            self._moved = 0.0
            self._last_xy = (e["x"], e["y"])
        elif et == "pointer_move" and self._down is not None:
            dx, dy = e["x"] - self._last_xy[0], e["y"] - self._last_xy[1]
            self._last_xy = (e["x"], e["y"])
            self._moved += abs(dx) + abs(dy)
            _, _, button, shift = self._down
            self._turn("pan" if button == 2 or shift else "orbit", dx, dy)
        elif et == "pointer_up" and self._down is not None:
            x0, y0, button, _ = self._down
            self._down = None
            if button == 1 and abs(e["x"] - x0) + abs(e["y"] - y0) <= CLICK_TOLERANCE_PX:
                self.pick(e["x"], e["y"])

    def _turn(self, cmd: str, dx: float, dy: float) -> None:
        """Orbit or pan by a drag of (dx, dy) px, or zoom by a wheel's dx: as a control
        message when ``on_control`` is set, else on the window's own controller."""
        c, h = self.controller, self.renderer.height
        if self.on_control is None:
            {"orbit": lambda: c.orbit(dx, dy), "pan": lambda: c.pan(dx, dy, h), "zoom": lambda: c.zoom(dx)}[cmd]()
        elif cmd == "orbit":
            self.on_control({"cmd": "orbit", "azimuth_deg": -dx * c.orbit_deg_per_px,
                             "elevation_deg": dy * c.orbit_deg_per_px})
        elif cmd == "pan":
            self.on_control({"cmd": "pan", "right": -dx / max(h, 1), "up": dy / max(h, 1)})
        else:
            self.on_control({"cmd": "zoom", "factor": 1.0 / c.zoom_per_wheel ** float(dx)})
        self._dirty = True

    def pick(self, x: float, y: float) -> Optional[int]:
        """Pick at logical window coordinates (scaled by the canvas' pixel ratio)."""
        ratio = float(self.canvas.get_pixel_ratio())
        slot = self.renderer.pick(x, y, ratio)
        self.picks.append(slot)
        self.on_pick(slot, x, y)
        return slot

    def process_events(self) -> None:
        self.canvas._process_events()

    def step(self, frame: FrameInput) -> bool:
        """Render, present and handle input once. False when the window was closed."""
        if self.canvas.get_closed():
            return False
        self.process_events()
        stats = self.renderer.render(frame, self.camera)
        self.last_stats = stats
        self._image = self.renderer.read_image()
        self.canvas.force_draw()
        self.frames += 1
        now = time.perf_counter()
        dt = now - self._t_last
        self._t_last = now
        self._fps = 0.8 * self._fps + 0.2 * (1.0 / dt) if dt > 0 and self._fps else (1.0 / dt if dt > 0 else 0.0)
        self.last_title = self.status_line(frame, stats)
        self.canvas.set_title(self.last_title)
        self._dirty = False
        return not self.canvas.get_closed()

    def status_line(self, frame: FrameInput, stats: FrameStats) -> str:
        t = stats.timings_ms
        gpu = t.get("gpu_compute", 0.0) + t.get("gpu_draw", 0.0)
        parts = [self.title, f"{self._fps:.1f} fps", f"{frame.size:,} pts", f"{self.renderer.tier}",
                 f"cpu {t.get('cpu_total', 0.0):.1f} ms"]
        if gpu:
            parts.append(f"gpu {gpu:.1f} ms")
        if stats.drawn is not None:
            parts.append(f"drawn {stats.drawn:,}")
        return " | ".join(parts)

    def close(self) -> None:
        try:
            self.canvas.close()
            self.canvas._process_events()
        except Exception:
            pass
        # The window's wgpu surface goes now, while its display connection lives: left to the
        # garbage collector it can go after the display (an Xvfb that ended) and crash the
        # process in wgpuSurfaceRelease (seen in a test run: a segfault in a later test).
        release = getattr(getattr(self._ctx, "_wgpu_context", None), "_release", None)
        if callable(release):
            try:
                release()
            except Exception:  # noqa: BLE001 - closing must not fail
                pass
