"""Picking: the pick pass, the block readback and the strategies."""
import numpy as np
import pytest

from pointflow.render.camera import Camera, project_to_pixels
from pointflow.render.wgpu_tier import resolve_pick

from .helpers import cfg, frame

pytestmark = pytest.mark.gpu

CAM = Camera(eye=[0.0, -10.0, 0.0], target=[0.0, 0.0, 0.0], near=1.0, far=100.0)


def _px(cam, p, w, h):
    px, py, _, _ = project_to_pixels(np.asarray(p, np.float64).reshape(-1, 3), cam.view_proj(w, h), w, h)
    return px, py


def test_pick_returns_point_under_cursor_front_before_behind(make_renderer):
    # slots 0..2 spread on screen; slot 3 sits behind slot 1 on the same ray; slot 4 in front of slot 2
    pts = np.array([[-2.0, 0.0, 0.0], [0.0, 0.0, 0.0], [2.0, 0.0, 1.0], [0.0, 6.0, 0.0], [2.0 * 0.5, -5.0, 0.5]])
    cap, head = 8, 6
    r = make_renderer(cfg(point_size=5.0, pick_radius=4), cap)
    r.render(frame(pts, capacity=cap, head=head), CAM)
    slot = lambda i: (head + i) % cap
    px, py = _px(CAM, pts, 320, 240)
    assert r.pick(px[0], py[0]) == slot(0)
    assert r.pick(px[1], py[1]) == slot(1)              # slot 3 is behind it: hidden
    assert r.pick(px[2], py[2]) == slot(4)              # slot 4 is in front of slot 2
    assert r.pick(px[0] + 3.0, py[0] + 1.0) == slot(0)  # within the radius
    assert r.pick(5.0, 5.0) is None                     # nothing there
    assert r.pick(-50.0, -50.0) is None                 # outside the window
    # the pick does not disturb the frame
    before = r.read_image()
    r.pick(px[1], py[1])
    assert np.array_equal(before, r.read_image())


def test_pick_hidpi_scaling(make_renderer):
    """Window coordinates are logical pixels; the target is pixel_ratio times larger."""
    pts = np.array([[-1.0, 0.0, -0.5], [1.5, 0.0, 0.7]])
    r = make_renderer(cfg(size=[640, 480], point_size=6.0, pick_radius=2), 2)
    r.render(frame(pts), CAM)
    px, py = _px(CAM, pts, 640, 480)
    for i in range(2):
        assert r.pick(px[i] / 2.0, py[i] / 2.0, pixel_ratio=2.0) == i
        assert r.pick(px[i] / 2.0, py[i] / 2.0, pixel_ratio=1.0) is None   # unscaled: wrong place


def test_pick_strategies(make_renderer):
    # three points near each other on screen with different importance and age
    pts = np.array([[0.0, 0.0, 0.0], [0.15, 0.0, 0.0], [-0.15, 0.0, 0.0]])
    imp = np.array([0.1, 0.9, 0.5], np.float32)
    t = np.array([1000.0, 500.0, 2000.0])
    for strategy, want in (("nearest", 0), ("highest_importance", 1), ("recent_first", 2)):
        r = make_renderer(cfg(point_size=3.0, pick_radius=8, pick_strategy=strategy), 3)
        r.render(frame(pts, importance=imp, t_ms=t, now_ms=2000.0), CAM)
        px, py = _px(CAM, pts[:1], 320, 240)
        assert r.pick(px[0], py[0]) == want, strategy


def test_resolve_pick_tie_breaks():
    ids = np.zeros((3, 3), np.uint32)
    attrs = np.zeros((3, 3, 4), np.float32)
    ids[0, 1], ids[1, 0] = 8, 5                       # slots 7 and 4, both 1 px from the centre texel
    attrs[0, 1, 0], attrs[1, 0, 0] = 0.5, 0.5
    assert resolve_pick(ids, attrs, 0, 0, 1.5, 1.5, 2.0, "nearest") == 4      # equal distance and depth: lower slot
    attrs[0, 1, 0] = 0.4
    assert resolve_pick(ids, attrs, 0, 0, 1.5, 1.5, 2.0, "nearest") == 7      # equal distance: nearer depth
    assert resolve_pick(ids, attrs, 0, 0, 1.5, 1.5, 0.0, "nearest") is None   # radius 0: the texel under the cursor only
    ids[1, 1] = 3
    assert resolve_pick(ids, attrs, 0, 0, 1.5, 1.5, 0.0, "nearest") == 2
