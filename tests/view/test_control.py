"""Each view control message changes the next frame as it should, reads back, and a bad one
is refused with its argument named while the pipeline goes on (real processes, cpu tier).

Scene (world metres): a dense 20 x 20 m plane with a step, z = 0 for x < 10 and z = 3 for
x >= 10, plus three lone points at z = 0 outside it; seen from straight above."""
from __future__ import annotations

import math
import os
import sys

import numpy as np
import pytest
import yaml
from PIL import Image

from pointflow import Pipeline
from pointflow.render import colormap
from pointflow.render.camera import Camera, project_to_pixels
from pointflow.render.view.protocol import ControlError

sys.path.insert(0, os.path.dirname(os.path.dirname(__file__)))

W, H = 160, 120
EYE, TARGET, UP = [10.0, 10.0, 40.0], [10.0, 10.0, 0.0], [0.0, 1.0, 0.0]
LONE = np.array([[-5.0, 5.0, 0.0], [-5.0, 15.0, 0.0], [25.0, 27.0, 0.0]])
BG = np.round(np.array([0.02, 0.02, 0.05]) * 255).astype(np.uint8)


def _scene(path) -> str:
    g = np.stack(np.meshgrid(np.arange(0, 20, 0.2), np.arange(0, 20, 0.2)), -1).reshape(-1, 2)
    z = np.where(g[:, 0] >= 10.0 - 1e-9, 3.0, 0.0)
    pts = np.vstack([np.column_stack([g, z]), LONE])
    f = os.path.join(path, "scene.npz")
    np.savez(f, x=pts[:, 0], y=pts[:, 1], z=pts[:, 2], intensity=np.arange(len(pts), dtype=np.float32))
    return f


def _config(scene: str, **render) -> dict:
    r = {"backend": "cpu", "size": [W, H], "point_size": 2, "color_by": "intensity",
         "output": {"every_n_frames": 100000}}
    r.update(render)
    return {"source": {"transport": "file", "name": "scene", "options": {"path": scene, "realtime": False}},
            "ring": {"max_points": 20000, "extra_channels": []}, "cadence": {"target_hz": 30}, "render": r}


def _px(cam: Camera, p) -> tuple[int, int]:
    px, py, _, _ = project_to_pixels(np.asarray([p], np.float64), cam.view_proj(W, H), W, H)
    return int(px[0]), int(py[0])


def _frame(pipe, tmp_path, name) -> np.ndarray:
    return np.asarray(Image.open(pipe.save_frame(str(tmp_path / f"{name}.png"))))[..., :3]


def _is_bg(rgb) -> bool:
    return bool((np.asarray(rgb) == BG).all())


def _wait_loaded(pipe, n):
    pipe.wait(90, until=lambda: pipe.stats()["stages"]["render"].get("drawn_count", 0) >= n)
    assert pipe.stats()["stages"]["render"].get("drawn_count", 0) >= n, "the scene never reached the renderer"


def test_each_control_message_shows_in_the_next_frame(tmp_path):
    scene = _scene(str(tmp_path))
    n = 100 * 100 + len(LONE)
    with Pipeline.from_dict(_config(scene), out_dir=str(tmp_path)) as pipe:
        _wait_loaded(pipe, n)
        # camera: set it; the reply comes once a frame shows it, and reads back
        st = pipe.camera(eye=EYE, target=TARGET, up=UP, fov_deg=60.0)
        assert st["drawn_version"] >= st["version"] >= 1
        assert st["camera"] == {"mode": "fixed", "eye": EYE, "target": TARGET, "up": UP, "fov_deg": 60.0, "follow": None,
                                "follow_anchor": None}
        cam = Camera(eye=EYE, target=TARGET, up=UP, fov_deg=60.0)
        img_a = _frame(pipe, tmp_path, "a")
        assert not _is_bg(img_a[H // 2, W // 2]), "the plane is under the image centre"

        # colour by z with a fixed range: the colours the lookup table gives
        st = pipe.style(color_by="z", colormap="viridis", color_range=[0.0, 3.0])
        assert st["style"]["color_by"] == "z" and st["style"]["colormap"] == "viridis"
        img = _frame(pipe, tmp_path, "z")
        lut = colormap.lut("viridis")[:, :3]
        low, high = _px(cam, [5.0, 10.0, 0.0]), _px(cam, [15.0, 10.0, 3.0])
        np.testing.assert_array_equal(img[low[1], low[0]], lut[0])
        np.testing.assert_array_equal(img[high[1], high[0]], lut[255])
        lone = _px(cam, LONE[0])
        np.testing.assert_array_equal(img[lone[1], lone[0]], lut[0])

        # the camera moves: the plane's far edge is now at the image centre
        pipe.camera(eye=[20.0, 10.0, 40.0], target=[20.0, 10.0, 0.0])
        cam_b = Camera(eye=[20.0, 10.0, 40.0], target=[20.0, 10.0, 0.0], up=UP, fov_deg=60.0)
        img_b = _frame(pipe, tmp_path, "b")
        assert not (img_b == img).all(), "moving the camera changed nothing"
        x, y = _px(cam_b, [25.0, 10.0, 0.0])  # nothing there
        assert _is_bg(img_b[y, x])
        x, y = _px(cam_b, [15.0, 10.0, 3.0])
        np.testing.assert_array_equal(img_b[y, x], lut[255])
        x, y = _px(cam_b, LONE[2])
        np.testing.assert_array_equal(img_b[y, x], lut[0])

        # orbit, zoom, pan: read back where the eye went
        pipe.camera(eye=[10.0, -10.0, 20.0], target=TARGET, up=[0.0, 0.0, 1.0])
        st = pipe.orbit(azimuth_deg=90.0)
        np.testing.assert_allclose(st["camera"]["eye"], [30.0, 10.0, 20.0], atol=1e-9)
        st = pipe.zoom(2.0)
        np.testing.assert_allclose(st["camera"]["eye"], [20.0, 10.0, 10.0], atol=1e-9)
        st = pipe.pan(right=0.5)
        d = np.subtract(st["camera"]["target"], TARGET)
        visible_h = 2.0 * math.dist([20.0, 10.0, 10.0], TARGET) * math.tan(math.radians(30.0))
        assert np.linalg.norm(d) == pytest.approx(0.5 * visible_h, rel=1e-9)
        assert abs(d[2]) < 1e-9

        # point size and shape, on a lone point seen from above again
        pipe.camera(eye=EYE, target=TARGET, up=UP)
        x, y = _px(cam, LONE[1])

        def lone_pixels(name):
            im = _frame(pipe, tmp_path, name)[y - 8:y + 9, x - 8:x + 9]
            return int((im != BG).any(axis=-1).sum())

        pipe.style(point_size=8.0)
        square = lone_pixels("square8")
        pipe.style(point_shape="round")
        round_ = lone_pixels("round8")
        pipe.style(point_size=2.0, point_shape="square")
        small = lone_pixels("square2")
        assert square == 64 and small == 4 and 40 <= round_ < 64, (square, round_, small)

        # eye-dome lighting darkens the low side of the step, nowhere brightens
        off = _frame(pipe, tmp_path, "edl_off").astype(int)
        st = pipe.style(edl=True, edl_strength=1.0)
        assert st["style"]["edl"] is True
        on = _frame(pipe, tmp_path, "edl_on").astype(int)
        assert (on <= off).all()
        darker = on.sum(axis=-1) < off.sum(axis=-1) - 10
        edge_px = abs(_px(cam, [10.0, 20.0, 0.0])[1] - _px(cam, [10.0, 0.0, 0.0])[1])  # the low side's edge on screen
        assert darker.sum() >= 0.8 * edge_px, "EDL did not darken the step's edge"
        assert (off[darker] == lut[0]).all(), "EDL darkened something other than the low side of the step"
        ys, xs = np.nonzero(darker)
        assert (np.abs(xs - _px(cam, [10.0, 10.0, 0.0])[0]) <= 3).all()
        fx, fy = _px(cam, [5.0, 10.0, 0.0])  # flat, far from the edge: unchanged
        assert (on[fy, fx] == off[fy, fx]).all()
        pipe.style(edl=False)

        # time window: points older than it are not drawn; off again, they are
        pipe.style(time_window_ms=1.0)
        assert (_frame(pipe, tmp_path, "tw") == BG).all()
        pipe.style(time_window_ms=0.0)
        assert not (_frame(pipe, tmp_path, "tw0") == BG).all()

        # fit: back to framing the data
        st = pipe.fit()
        assert st["camera"]["mode"] == "auto" and st["camera_drawn"]["eye"] != EYE

        # read back and save as a view: block
        pipe.camera(eye=EYE, target=TARGET, up=UP)
        pipe.style(color_by="z", colormap="grayscale", point_size=3.0)
        path = pipe.save_view(str(tmp_path / "view.yaml"))
        render = pipe.stats()["stages"]["render"]
        assert render["restarts"] == 0
    block = yaml.safe_load(open(path))
    assert block["view"]["camera"]["eye"] == EYE
    assert block["view"]["style"]["colormap"] == "grayscale"

    # a later run starts from the saved view
    cfg = _config(scene)
    cfg["view"] = block["view"]
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path / "again")) as pipe:
        _wait_loaded(pipe, n)
        st = pipe.view_state()
        assert st["camera"]["eye"] == EYE and st["style"]["colormap"] == "grayscale"
        pipe.wait(30, until=lambda: pipe.view_state()["camera_drawn"] is not None)
        assert pipe.view_state()["camera_drawn"]["eye"] == EYE
        img = _frame(pipe, tmp_path, "again")
        lo, hi = _px(cam, [5.0, 10.0, 0.0]), _px(cam, [15.0, 10.0, 3.0])
        g = colormap.lut("grayscale")[:, :3]
        assert (img[lo[1], lo[0]] == g[0]).all() and (img[hi[1], hi[0]] == g[255]).all()


def test_bad_control_messages_are_refused_and_the_pipeline_goes_on(tmp_path):
    scene = _scene(str(tmp_path))
    with Pipeline.from_dict(_config(scene), out_dir=str(tmp_path)) as pipe:
        _wait_loaded(pipe, 1000)
        v0 = pipe.view_state()["version"]
        bad = [
            (lambda: pipe.camera(eye=[float("nan"), 0.0, 1.0]), "camera.eye", "finite"),
            (lambda: pipe.camera(fov_deg=180.0), "camera.fov_deg", "(0, 180)"),
            (lambda: pipe.style(color_by="hieght"), "style.color_by", "ring.extra_channels"),
            (lambda: pipe.style(colormap="jet"), "style.colormap", "turbo, viridis, grayscale"),
            (lambda: pipe.style(point_size=-1), "style.point_size", "(0, 32]"),
            (lambda: pipe.zoom(0.0), "zoom.factor", "> 0"),
            (lambda: pipe.control({"cmd": "spin"}), "cmd", "camera, orbit"),
            (lambda: pipe.control({"cmd": "camera", "eyes": [0, 0, 1]}), "camera.eyes", "unknown argument"),
            (lambda: pipe.visible("scene", on=False), "visible.source", "one source"),
            (lambda: pipe.follow("base_link"), "follow.frame", "frames.fixed"),
        ]
        for call, key, words in bad:
            with pytest.raises(ControlError) as exc:
                call()
            assert exc.value.key == key and words in str(exc.value), str(exc.value)
            assert "\n" not in str(exc.value)
        assert pipe.view_state()["version"] == v0, "a refused message changed the view"
        st = pipe.style(color_by="z")  # still steerable, nothing restarted
        assert st["style"]["color_by"] == "z" and st["drawn_version"] == st["version"]
        refused = lambda: pipe.stats()["stages"]["render"]["drops"].get("bad_control", 0)
        pipe.wait(20, until=lambda: refused() >= len(bad))  # counted with the next heartbeat
        assert refused() == len(bad) and pipe.stats()["stages"]["render"]["restarts"] == 0


def test_hide_and_show_a_source(tmp_path):
    files = {}
    for name, x0 in (("left", 0.0), ("right", 12.0)):
        g = np.stack(np.meshgrid(np.arange(x0, x0 + 8, 0.25), np.arange(6, 14, 0.25)), -1).reshape(-1, 2)
        files[name] = str(tmp_path / f"{name}.npz")
        np.savez(files[name], x=g[:, 0], y=g[:, 1], z=np.zeros(len(g)))
    cfg = _config(files["left"])
    cfg["sources"] = [{"transport": "file", "name": n, "options": {"path": f, "realtime": False}}
                      for n, f in files.items()]
    del cfg["source"]
    cfg["view"] = {"camera": {"eye": EYE, "target": TARGET, "up": UP}}
    cam = Camera(eye=EYE, target=TARGET, up=UP, fov_deg=60.0)
    left, right = _px(cam, [4.0, 10.0, 0.0]), _px(cam, [16.0, 10.0, 0.0])
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path)) as pipe:
        pipe.wait(90, until=lambda: pipe.stats()["ring"]["total_points"] >= 2 * 32 * 32)
        assert pipe.stats()["ring"]["total_points"] >= 2 * 32 * 32, "the sources' points never reached the ring"
        pipe.style(point_size=2.0)  # any message: returns once a frame drawn after it shows both
        both = _frame(pipe, tmp_path, "both")
        assert not _is_bg(both[left[1], left[0]]) and not _is_bg(both[right[1], right[0]])
        st = pipe.visible("right", on=False)
        assert st["hidden_sources"] == ["right"]
        img = _frame(pipe, tmp_path, "left_only")
        assert _is_bg(img[right[1], right[0]]) and (img[left[1], left[0]] == both[left[1], left[0]]).all()
        half = W // 2  # the right source is drawn only right of the centre
        assert (img[:, half:] == BG).all() and (img[:, :half] == both[:, :half]).all()
        with pytest.raises(ControlError) as exc:
            pipe.visible("middle", on=False)
        assert exc.value.key == "visible.source" and "left, right" in str(exc.value)
        st = pipe.visible("right")
        assert st["hidden_sources"] == []
        assert (_frame(pipe, tmp_path, "both_again") == both).all()
        assert pipe.view_state()["view_block"].get("hidden_sources") is None
        pipe.visible("left", on=False)
        assert pipe.view_state()["view_block"]["hidden_sources"] == ["left"]
        render = pipe.stats()["stages"]["render"]
        assert render.get("nonfinite_skipped", 0) == 0, "hidden points were counted as non-finite input"


def test_follow_a_moving_frame(tmp_path):
    """The synthetic lidar drives along the street (odom -> base_link at 20 Hz): a camera
    that follows base_link keeps its offset from it while the target moves with it."""
    cfg = {"source": {"transport": "synthetic", "options": {"scan_hz": 10, "points_per_scan": 5000,
                                                            "drive_speed": 8, "mode": "moving"}},
           "frames": {"fixed": "odom", "tf_wait_ms": 200}, "ring": {"max_points": 50000},
           "cadence": {"target_hz": 20},
           "render": {"backend": "cpu", "size": [W, H], "output": {"every_n_frames": 100000}}}
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path)) as pipe:
        pipe.wait(90, until=lambda: pipe.stats()["frames"] >= 2)
        pipe.camera(eye=[-20.0, -20.0, 15.0], target=[0.0, 0.0, 0.0], up=[0.0, 0.0, 1.0])
        st = pipe.follow("base_link")
        pipe.wait(30, until=lambda: pipe.view_state().get("follow_status") == "following")
        st = pipe.view_state()
        assert st["camera"]["follow"] == "base_link" and st["follow_status"] == "following"
        offset = np.subtract(st["camera"]["eye"], st["camera"]["target"])
        np.testing.assert_allclose(offset, [-20.0, -20.0, 15.0], atol=1e-9)
        seen = []
        for _ in range(3):
            pipe.wait(1.0)
            d = pipe.view_state()["camera_drawn"]
            np.testing.assert_allclose(np.subtract(d["eye"], d["target"]), offset, atol=1e-6)
            seen.append(d["target"])
        assert np.linalg.norm(np.subtract(seen[-1], seen[0])) > 1.0, f"the target did not move with base_link: {seen}"
        st = pipe.pan(right=0.2)  # still works while following: the target moves off the frame's origin
        moved = np.subtract(st["camera"]["target"], st["camera"]["follow_anchor"])
        assert np.linalg.norm(moved) > 1.0 and st["camera"]["follow"] == "base_link"
        d = pipe.view_state()["camera_drawn"]
        np.testing.assert_allclose(np.subtract(d["eye"], d["target"]), offset, atol=1e-6)
        st = pipe.follow(None)
        assert st["camera"]["follow"] is None and "follow_status" not in st
        still = pipe.view_state()["camera_drawn"]["target"]
        pipe.wait(1.0)
        assert pipe.view_state()["camera_drawn"]["target"] == still


def test_the_view_survives_a_render_restart(tmp_path):
    import signal

    scene = _scene(str(tmp_path))
    with Pipeline.from_dict(_config(scene), out_dir=str(tmp_path)) as pipe:
        _wait_loaded(pipe, 1000)
        pipe.camera(eye=EYE, target=TARGET, up=UP)
        pipe.style(color_by="z", colormap="viridis", color_range=[0.0, 3.0])
        before = pipe.view_state()
        old = pipe.stats()["stages"]["render"]["pid"]
        os.kill(old, signal.SIGKILL)
        pipe.wait(90, until=lambda: pipe.stats()["stages"]["render"]["pid"] != old
                  and pipe.stats()["stages"]["render"]["ready"])
        assert pipe.stats()["stages"]["render"]["restarts"] == 1
        pipe.wait(60, until=lambda: pipe.view_state()["drawn_version"] >= before["version"])
        after = pipe.view_state()
        assert after["camera"] == before["camera"] and after["style"] == before["style"]
        assert after["drawn_version"] >= before["version"]
        cam = Camera(eye=EYE, target=TARGET, up=UP, fov_deg=60.0)
        img = _frame(pipe, tmp_path, "restarted")
        hi = _px(cam, [15.0, 10.0, 3.0])
        np.testing.assert_array_equal(img[hi[1], hi[0]], colormap.lut("viridis")[255, :3])
