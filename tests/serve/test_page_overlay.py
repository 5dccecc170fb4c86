"""The page's orientation and annotations in a real browser (Debian's chromium, headless):
axes, grid and compass drawn from each frame's camera and switchable; the colour legend's
range and colours equal the style's range and the render stage's LUT; a pick's marker at
the point's projected pixel and a measure line between two picks; help on ``?``; the
stats line's names and tooltip; the favicon; "run ended" when the pipeline stops; a seek
while paused changes the picture and a step moves one message."""
from __future__ import annotations

import json
import os
import time

import numpy as np
import pytest

from pointflow import Pipeline
from pointflow.render.camera import Camera, project_to_pixels
from pointflow.render.colormap import lut

from .browser import frames, new_page, wait_frames
from .helpers import scene_pipeline, TOKEN, base_url, config, http_get, serve_stats

KNOWN = (1.5, -2.25, 3.0)


@pytest.fixture(scope="module")
def pipe(tmp_path_factory):
    d = tmp_path_factory.mktemp("overlay")
    with scene_pipeline(str(d)) as p:
        yield p


def _open(browser, pipe, hash_: str = "", **kw):
    page = new_page(browser, **kw)
    page.goto(f"{base_url(pipe)}/?token={TOKEN}{hash_}")
    wait_frames(page, 1)
    return page


def _control(page, **msg) -> None:
    page.evaluate(f"window.pointflowView.control({json.dumps(msg)})")


def _settle(page, quiet_s: float = 1.5, timeout_s: float = 60.0) -> None:
    end = time.monotonic() + timeout_s
    last, t = frames(page), time.monotonic()
    while time.monotonic() < end:
        time.sleep(0.25)
        n = frames(page)
        if n != last:
            last, t = n, time.monotonic()
        elif time.monotonic() - t >= quiet_s:
            return


def _look(page, eye, target, up=(0.0, 0.0, 1.0)) -> dict:
    """Set the camera and wait for a frame drawn with it; returns that frame's camera."""
    _control(page, cmd="camera", eye=list(eye), target=list(target), up=list(up), fov_deg=60.0)
    page.wait_for_function(f"""(() => {{ const c = window.pointflowView.camera();
        return c && Math.abs(c.eye[0] - {eye[0]}) < 1e-9 && Math.abs(c.eye[1] - {eye[1]}) < 1e-9
               && Math.abs(c.eye[2] - {eye[2]}) < 1e-9; }})()""", timeout=60000)
    _settle(page)
    return page.evaluate("window.pointflowView.camera()")


def _px(cam: dict, size, p) -> tuple[float, float]:
    """Where the render stage's projection (render/camera.py) puts world point ``p``."""
    c = Camera(eye=cam["eye"], target=cam["target"], up=cam["up"], fov_deg=cam["fov_deg"], near=cam["near"],
               far=cam["far"])
    w, h = size
    px, py, _, _ = project_to_pixels(np.asarray([p], np.float64), c.view_proj(w, h), w, h)
    return float(px[0]), float(py[0])


def _overlay_rgba(page, x: float, y: float, r: int = 1) -> np.ndarray:
    """The overlay canvas's pixels around (x, y) (canvas pixels), as (n, 4) RGBA."""
    data = page.evaluate(f"""(() => {{ const c = document.getElementById('overlay');
        const d = c.getContext('2d').getImageData({int(x) - r}, {int(y) - r}, {2 * r + 1}, {2 * r + 1}).data;
        return Array.from(d); }})()""")
    return np.asarray(data, np.uint8).reshape(-1, 4)


def _reddish(px: np.ndarray) -> bool:
    """Any opaque pixel that is the X axis's red (not the grid's grey)."""
    c = px.astype(int)
    return bool(((c[:, 3] > 200) & (c[:, 0] > 150) & (c[:, 0] - c[:, 1] > 60)).any())


def _size(page) -> tuple[int, int]:
    return tuple(page.evaluate("[document.getElementById('overlay').width, document.getElementById('overlay').height]"))


def test_axes_grid_compass_drawn_from_the_camera_and_switchable(browser, pipe):
    page = _open(browser, pipe)
    cam = _look(page, eye=(14.0, -18.0, 12.0), target=(0.0, 0.0, 0.0))
    size = _size(page)
    lay = page.evaluate("window.pointflowView.overlay()")
    assert lay["spacing"] in (1, 2, 5, 10) or np.log10(lay["spacing"]) % 1 in (0.0,)  # a 1-2-5 step
    half = lay["axisLength"] * 0.6
    for axis, p in enumerate(((half, 0, 0), (0, half, 0), (0, 0, half))):
        x, y = _px(cam, size, p)
        px = _overlay_rgba(page, x, y, 1)
        opaque = px[px[:, 3] > 200]
        assert len(opaque), f"axis {'XYZ'[axis]}: nothing drawn at its projected pixel ({x:.1f}, {y:.1f})"
        rgb = opaque[:, :3].astype(int).mean(axis=0)
        assert rgb.argmax() == axis and rgb[axis] > rgb.max(initial=0) - 1 and rgb[axis] > 150, (axis, rgb)
    # the grid: a grid line (z = 0, x = one spacing) is drawn, away from the axes
    sp = lay["spacing"]
    gx, gy = _px(cam, size, (sp, -3 * sp, 0.0))
    assert _overlay_rgba(page, gx, gy, 1)[:, 3].max() > 0, "no grid line where x = one spacing crosses y = -3"
    # each switched off: its pixels go (the frame is not re-rendered: the overlay is redrawn)
    n0 = frames(page)
    page.uncheck("#show_axes")
    x, y = _px(cam, size, (half, 0, 0))
    assert not _reddish(_overlay_rgba(page, x, y, 1)), "axes still drawn after switching them off"
    page.uncheck("#show_grid")
    assert _overlay_rgba(page, gx, gy, 1)[:, 3].max() == 0, "grid still drawn after switching it off"
    cx, cy = 14 + 28, size[1] - 14 - 28  # the compass's centre (overlay.js, scale 1 at this size)
    assert _overlay_rgba(page, cx, cy, 3)[:, 3].max() > 0
    page.uncheck("#show_compass")
    assert _overlay_rgba(page, cx, cy, 3)[:, 3].max() == 0
    assert frames(page) - n0 <= 2, "switching the overlay re-rendered the picture"
    assert "axes=0" in page.url and "grid=0" in page.url and "compass=0" in page.url  # the state is in the URL
    page.context.close()
    # from the URL: a page opened with #axes=0 draws no axes
    page = _open(browser, pipe, hash_="#axes=0&legend=0")
    cam = _look(page, eye=(14.0, -18.0, 12.0), target=(0.0, 0.0, 0.0))
    assert not page.is_checked("#show_axes") and page.is_checked("#show_grid")
    x, y = _px(cam, _size(page), (half, 0, 0))
    assert not _reddish(_overlay_rgba(page, x, y, 1))
    assert page.locator("#legend").is_hidden()
    assert not page.errors, page.errors
    page.context.close()


def test_legend_follows_the_style_with_the_render_stages_lut(browser, pipe):
    page = _open(browser, pipe)
    try:
        # the scene's intensity is 0..6400 (one per point): the auto range is the data's
        page.wait_for_function("window.pointflowView.legend() && !document.getElementById('legend').hidden",
                               timeout=60000)
        lg = page.evaluate("window.pointflowView.legend()")
        assert lg["color_by"] == "intensity" and lg["auto"] and lg["range"] == [0.0, 6400.0], lg
        text = page.locator("#legend").inner_text()
        lines = text.split("\n")  # the ticks with the decimals a range of 6400 needs: none
        assert "intensity" in text and "turbo" in text and "0" in lines and "6400" in lines, text
        _check_bar(page, "turbo")
        # a fixed range and another colormap: the legend follows
        _control(page, cmd="style", color_range=[100.0, 2500.0], colormap="viridis")
        page.wait_for_function("document.getElementById('legend').dataset.hi === '2500'", timeout=60000)
        text = page.locator("#legend").inner_text()
        lines = text.split("\n")
        assert "100" in lines and "2500" in lines and "viridis" in text and "auto" not in text, text
        _check_bar(page, "viridis")
        # z, auto: the grid's 0 and the known point's 3
        _control(page, cmd="style", color_by="z", color_range="auto", colormap="turbo")
        page.wait_for_function("document.getElementById('legend').dataset.hi === '3'", timeout=60000)
        assert page.evaluate("window.pointflowView.legend().range") == [0.0, 3.0]
        # no colormap: no legend
        _control(page, cmd="style", color_by="none")
        page.wait_for_function("document.getElementById('legend').hidden", timeout=60000)
    finally:
        _control(page, cmd="style", color_by="intensity", color_range="auto", colormap="turbo")
        page.wait_for_function("window.pointflowView.state().style.color_by === 'intensity'", timeout=60000)
        page.context.close()


def _check_bar(page, name: str) -> None:
    page.wait_for_function(f"document.getElementById('legend').dataset.colormap === '{name}'", timeout=60000)
    bar = np.asarray(page.evaluate("""Array.from(document.getElementById('legend_bar').getContext('2d')
                                         .getImageData(0, 0, 256, 1).data)"""), np.uint8).reshape(256, 4)
    ref = lut(name)
    for i in (0, 37, 128, 200, 255):
        assert (bar[i, :3] == ref[i, :3]).all(), (name, i, bar[i], ref[i])


def test_pick_marker_and_measure_line_in_the_picture(browser, pipe):
    page = _open(browser, pipe)
    cam = _look(page, eye=(KNOWN[0] + 4.0, KNOWN[1] - 6.0, 14.0), target=KNOWN)
    size = _size(page)
    kx, ky = _px(cam, size, KNOWN)
    box = page.locator("#view").bounding_box()
    sx, sy = box["width"] / size[0], box["height"] / size[1]
    hit = None
    for dx, dy in ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (1, 1)):
        page.evaluate("window.pointflowView.lastPick = null")
        page.mouse.click(box["x"] + (kx + dx) * sx, box["y"] + (ky + dy) * sy)
        page.wait_for_function("window.pointflowView.lastPick !== null", timeout=30000)
        pick = page.evaluate("window.pointflowView.lastPick")
        if pick["point"] is not None and np.allclose(pick["point"]["position"], KNOWN, atol=1e-4):
            hit = pick
            break
    assert hit is not None, f"no pick of the known point at ({kx:.1f}, {ky:.1f}) of {size}: {pick}"
    text = page.locator("#info").inner_text()
    assert "source: scene" in text and "intensity" in text, text  # every channel, the source by name
    # the marker: a ring of radius 7 around the point's projected pixel, its centre left clear
    ring = np.concatenate([_overlay_rgba(page, kx + ox, ky + oy, 0) for ox, oy in ((7, 0), (-7, 0), (0, 7), (0, -7))])
    assert (ring[:, 3] > 0).sum() >= 3, ring
    white = ring[(ring[:, 3] > 200) & (ring[:, :3].min(axis=1) > 200)]
    assert len(white), f"no white marker ring at the picked point's pixel ({kx:.1f}, {ky:.1f}): {ring}"
    # measure: the known point and a grid point; a yellow line joins their projected pixels
    page.select_option("#mode", "measure")
    assert page.locator("#info").is_hidden() and page.evaluate("window.pointflowView.marks().pick") is None
    other = None
    for target in [(kx, ky), (kx + 40, ky + 30)]:
        page.evaluate("window.pointflowView.lastPick = null")
        page.mouse.click(box["x"] + target[0] * sx, box["y"] + target[1] * sy)
        page.wait_for_function("window.pointflowView.lastPick !== null", timeout=30000)
        other = page.evaluate("window.pointflowView.lastPick")
    assert other["point"] is not None
    m = page.evaluate("window.pointflowView.marks().measure")
    assert len(m) == 2
    a, b = (_px(cam, size, p) for p in m)
    mid = ((a[0] + b[0]) / 2, (a[1] + b[1]) / 2)
    px = _overlay_rgba(page, *mid, 1)
    yellow = px[(px[:, 3] > 200) & (px[:, 0] > 200) & (px[:, 1] > 150) & (px[:, 2] < 120)]
    assert len(yellow), f"no measure line at the midpoint {mid}: {px}"
    d = float(np.linalg.norm(np.subtract(m[1], m[0])))
    assert "distance" in page.locator("#info").inner_text()
    assert abs(float(page.evaluate("document.getElementById('view').dataset.distance")) - d) < 1e-9
    # back to pick: the measurement and its panel go
    page.select_option("#mode", "pick")
    assert page.locator("#info").is_hidden() and page.evaluate("window.pointflowView.marks().measure") == []
    assert not (_overlay_rgba(page, *mid, 1)[:, 3] > 200).any()
    assert not page.errors, page.errors
    page.context.close()


def test_help_names_tooltip_favicon_and_refusal_text(browser, pipe):
    page = _open(browser, pipe)
    assert page.locator("#help").is_hidden()
    page.locator("#view").focus()
    page.keyboard.press("?")
    assert page.locator("#help").is_visible()
    assert "orbit" in page.locator("#help").inner_text() and "pick" in page.locator("#help").inner_text()
    page.keyboard.press("Escape")
    assert page.locator("#help").is_hidden()
    page.click("#help_button")
    assert page.locator("#help").is_visible()
    page.click("#help_close")
    # the size slider shows its value (once the view's state came; "…" before it)
    page.wait_for_function("document.getElementById('point_size_value').textContent !== '…'", timeout=30000)
    assert page.locator("#point_size_value").inner_text() == "3"
    # the stats line: "source: scene", drops explained in a tooltip
    page.wait_for_function("document.getElementById('stats').textContent.includes('source: scene')", timeout=30000)
    drops = page.locator("#stats span", has_text="drops")
    assert "skipped" in drops.get_attribute("title")
    # a refused follow says its key once
    _control(page, cmd="follow", frame="base_link")
    page.wait_for_function("document.getElementById('info').textContent.startsWith('refused')", timeout=30000)
    text = page.locator("#info").inner_text()
    assert text.startswith("refused: follow.frame: ") and text.count("follow.frame") == 1, text
    # the favicon: no 404
    code, body, headers = http_get(f"{base_url(pipe)}/favicon.ico", {"Cookie": page.context.cookies()[0]["name"]
                                                                     + "=" + TOKEN})
    assert code == 200 and headers["Content-Type"].startswith("image/svg+xml") and "<svg" in body
    assert not page.errors, page.errors
    page.context.close()


def test_a_restarting_view_server_is_not_a_run_that_ended(browser, pipe):
    """A view server killed and restarted by the supervisor drops the link (1006): the page
    reconnects and shows frames again; only the pipeline's own stop says "run ended"."""
    import signal

    page = _open(browser, pipe)
    st = serve_stats(pipe)
    os.kill(st["pid"], signal.SIGKILL)
    pipe.wait(60, until=lambda: serve_stats(pipe).get("alive") and serve_stats(pipe).get("port")
              and serve_stats(pipe).get("pid") != st["pid"])
    page.wait_for_function("document.getElementById('status').textContent.includes('reconnecting')"
                           " || window.pointflowView.frames() > 0", timeout=30000)
    n = frames(page)
    _control(page, cmd="orbit", azimuth_deg=10.0, elevation_deg=0.0)  # ignored while disconnected: retry
    end = time.monotonic() + 90
    while frames(page) <= n and time.monotonic() < end:
        time.sleep(0.5)
        _control(page, cmd="orbit", azimuth_deg=10.0, elevation_deg=0.0)
    assert frames(page) > n, "the page did not come back after the view server restarted"
    assert not page.evaluate("window.pointflowView.ended()")
    assert page.locator("#status").inner_text() != "run ended"
    page.context.close()


def _scans(path: str, n: int) -> str:
    d = os.path.join(path, "scans")
    os.makedirs(d, exist_ok=True)
    for i in range(n):
        g = np.arange(200, dtype=float)
        np.savez(os.path.join(d, f"s{i:03d}.npz"), x=np.full(200, float(i)), y=g / 20 - 5, z=np.sin(g / 10),
                 intensity=np.full(200, float(i), np.float32))
    return d


def test_seek_while_paused_shows_the_message_then_run_ended(browser, tmp_path):
    """Each scan is a line at x = its index; a small ring keeps only the newest two, so the
    picture shows where the replay is."""
    n = 40
    src = {"transport": "file", "name": "rec", "options": {"path": _scans(str(tmp_path), n), "rate": 10.0}}
    cfg = config(src, playback={"paused": True, "hold": True})
    cfg["ring"] = {"max_points": 400}
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path)) as pipe:
        page = new_page(browser)
        page.goto(f"{base_url(pipe)}/?token={TOKEN}")
        page.wait_for_function("window.pointflowView.playback() !== null", timeout=60000)
        assert page.evaluate("window.pointflowView.playback().paused") is True
        _control(page, cmd="camera", eye=[20.0, 0.0, 60.0], target=[20.0, 0.0, 0.0], up=[0.0, 1.0, 0.0])
        # seek to the middle while paused: the message there is shown, the replay stays paused
        page.evaluate("""() => { const s = document.getElementById('seek'); s.value = '500';
                                 s.dispatchEvent(new Event('change')); }""")
        pipe.wait(30, until=lambda: pipe.playback()["rec"]["index"] == n // 2)
        st = pipe.playback()["rec"]
        assert st["paused"] and st["index"] == n // 2, st
        page.wait_for_function("window.pointflowView.legend() && window.pointflowView.legend().range[1] === 20",
                               timeout=60000)  # the picture holds message 20 (intensity 20)
        _settle(page)
        assert page.evaluate("document.getElementById('seek').value") == "500"  # no snap back
        before = page.locator("#view").screenshot()
        # the step button: one message on, still paused
        page.click("#step")
        pipe.wait(30, until=lambda: pipe.playback()["rec"]["index"] == n // 2 + 1)
        page.wait_for_function("window.pointflowView.legend().range[1] === 21", timeout=60000)
        _settle(page)
        after = page.locator("#view").screenshot()
        assert before != after, "a step did not change the picture"
        # the '.' key steps too
        page.locator("#view").focus()
        page.keyboard.press(".")
        pipe.wait(30, until=lambda: pipe.playback()["rec"]["index"] == n // 2 + 2)
        assert pipe.playback()["rec"]["paused"]
    # the pipeline stopped: the page says so and does not try again
    page.wait_for_function("window.pointflowView.ended()", timeout=60000)
    assert page.locator("#status").inner_text() == "run ended"
    time.sleep(2.5)
    assert page.locator("#status").inner_text() == "run ended"  # no "reconnecting…"
    assert "run ended" in page.locator("#stats").inner_text()
    page.context.close()


def test_following_a_frame_not_known_is_said(browser, tmp_path):
    """With frames.fixed, following a frame no transform names (a typo) is accepted (its
    transforms may come later), and the page says it waits for them (it said nothing)."""
    from pointflow import Pipeline

    from .helpers import file_source, scene

    src = dict(file_source(scene(str(tmp_path))), frame_id="map")
    cfg = config(src, frames={"fixed": "map"})
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path)) as p:
        p.wait(90, until=lambda: p.stats()["stages"]["render"].get("drawn_count", 0) >= 6401)
        page = _open(browser, p)
        _control(page, cmd="follow", frame="nosuchframe")  # as the box sends it on Enter
        page.wait_for_function("(document.getElementById('follow').dataset.status || '').startsWith('waiting')",
                               timeout=60000)
        want = "waiting for transforms linking 'nosuchframe' to 'map'"
        assert want in page.locator("#follow").get_attribute("title")  # on the box, for as long as it waits
        text = page.locator("#info").inner_text()  # and said once in the info box
        assert text.startswith("follow nosuchframe: ") and want in text, text
        assert not page.errors, page.errors
        page.context.close()
