"""The optional window under Xvfb: it presents frames, orbits/pans/zooms and picks on click."""
import gc

import numpy as np
import pytest

from gpu_util import xvfb_display
from pointflow.render.camera import Camera, project_to_pixels

from .helpers import cfg, frame

pytestmark = pytest.mark.gpu


def _drag(win, x0: float, y0: float, x1: float, y1: float, shift: bool = False) -> None:
    """One left-button drag (shift: a pan) from (x0, y0) to (x1, y1), submitted to the canvas."""
    ev = dict(button=1, buttons=(1,), modifiers=("Shift",) if shift else ())
    win.canvas.submit_event(dict(event_type="pointer_down", x=x0, y=y0, **ev))
    win.canvas.submit_event(dict(event_type="pointer_move", x=x1, y=y1, **ev))
    win.canvas.submit_event(dict(event_type="pointer_up", x=x1, y=y1, **ev))


@pytest.fixture(scope="module")
def display():
    # one display for every raster method: glfw keeps its X connection across windows, and
    # a second private Xvfb in the same process made Xlib abort (BadRequest on a stale one)
    with xvfb_display() as d:
        yield d
        gc.collect()  # what the windows left goes while their display lives (not in a later test)


def test_window_presents_orbits_and_picks(make_renderer, display):
    from pointflow.render.window import PointWindow

    pts = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 1.0], [-2.0, 0.0, -1.0]])
    r = make_renderer(cfg(point_size=6.0, color=[1, 1, 1]), 3)
    cam = Camera(eye=[0.0, -10.0, 0.0], target=[0.0, 0.0, 0.0], near=0.5, far=100.0)
    picked = []
    win = PointWindow(r, cam, title="pf-test", on_pick=lambda slot, x, y: picked.append(slot))
    try:
        f = frame(pts)
        assert win.step(f)
        title = win.last_title
        assert "pf-test" in title and "3 pts" in title and "wgpu" in title and "fps" in title
        assert (r.read_image()[..., :3] == 255).all(axis=-1).sum() > 3 * 30

        # click on point 1 (no drag): picks slot 1
        px, py, _, _ = project_to_pixels(pts[1:2], cam.view_proj(320, 240), 320, 240)
        ev = dict(button=1, buttons=(1,), modifiers=())
        win.canvas.submit_event(dict(event_type="pointer_down", x=float(px[0]), y=float(py[0]), **ev))
        win.canvas.submit_event(dict(event_type="pointer_up", x=float(px[0]) + 1, y=float(py[0]), **ev))
        win.process_events()
        assert picked == [1]

        # left drag orbits about the target: distance kept, eye moved
        d0 = np.linalg.norm(win.camera.eye - win.camera.target)
        _drag(win, 100.0, 100.0, 160.0, 110.0)
        win.process_events()
        assert picked == [1]                                   # a drag is not a click
        assert np.allclose(win.camera.target, 0.0)
        assert np.isclose(np.linalg.norm(win.camera.eye - win.camera.target), d0)
        assert not np.allclose(win.camera.eye, cam.eye)
        before = r.read_image()
        assert win.step(f)
        assert not np.array_equal(before, r.read_image())      # the new view was drawn

        # shift-drag pans (target moves), wheel zooms (distance changes)
        _drag(win, 100.0, 100.0, 130.0, 100.0, shift=True)
        win.canvas.submit_event(dict(event_type="wheel", x=100.0, y=100.0, dx=0.0, dy=200.0, buttons=(), modifiers=()))
        win.process_events()
        assert not np.allclose(win.camera.target, 0.0)
        assert np.linalg.norm(win.camera.eye - win.camera.target) > d0 * 1.2
        assert win.step(f)
    finally:
        win.close()
    assert win.canvas.get_closed()


def test_window_input_is_view_control_messages(make_renderer, display):
    """In the render stage the window's drag and wheel travel as the view control messages
    Python sends (render/view/protocol.py), and applying them moves the camera exactly as the
    window's own controller would."""
    from pointflow.render.view import protocol as control
    from pointflow.render.camera import OrbitController
    from pointflow.render.window import PointWindow

    pts = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 1.0]])
    r = make_renderer(cfg(point_size=4.0, color=[1, 1, 1]), 2)
    cam = Camera(eye=[0.0, -10.0, 0.0], target=[0.0, 0.0, 0.0], near=0.5, far=100.0)
    sent = []
    state = {"s": control.ViewState.from_render_config(cfg())}

    def on_control(msg):
        sent.append(msg)
        state["s"] = control.apply(state["s"], msg, current=win.camera, height_px=r.height)
        c = state["s"].camera
        win.controller.camera = Camera(eye=c.eye, target=c.target, up=c.up, fov_deg=c.fov_deg, near=0.5, far=100.0)

    win = PointWindow(r, cam, title="pf-test", on_control=on_control)
    try:
        assert win.step(frame(pts))
        _drag(win, 100.0, 100.0, 160.0, 110.0)
        _drag(win, 100.0, 100.0, 130.0, 90.0, shift=True)
        win.canvas.submit_event(dict(event_type="wheel", x=100.0, y=100.0, dx=0.0, dy=200.0, buttons=(), modifiers=()))
        win.process_events()
        assert [m["cmd"] for m in sent] == ["orbit", "pan", "zoom"]
        direct = OrbitController(cam)
        direct.orbit(60.0, 10.0)
        direct.pan(30.0, -10.0, r.height)
        direct.zoom(200.0)
        assert np.allclose(win.camera.eye, direct.camera.eye, atol=1e-9)
        assert np.allclose(win.camera.target, direct.camera.target, atol=1e-9)
    finally:
        win.close()
