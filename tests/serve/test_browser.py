"""The page in a real browser (Debian's chromium, headless): it opens with the token and
shows the cloud; a drag changes the picture; a click on the known point shows its
coordinates; two tabs keep their own cameras; the timeline pauses and seeks a replay."""
from __future__ import annotations

import os
import time

import numpy as np
import pytest

from pointflow import Pipeline

from .browser import canvas_pixels, frames, new_page, wait_frames
from .helpers import scene_pipeline, TOKEN, base_url, config, serve_stats

KNOWN = (1.5, -2.25, 3.0)


@pytest.fixture(scope="module")
def pipe(tmp_path_factory):
    d = tmp_path_factory.mktemp("browser")
    with scene_pipeline(str(d)) as p:
        yield p


def _open(browser, pipe, **kw):
    page = new_page(browser, **kw)
    page.goto(f"{base_url(pipe)}/?token={TOKEN}")
    wait_frames(page, 1)
    return page


def _lit(img) -> int:
    return int((img.max(axis=2) > 60).sum())


def _settle(page, quiet_s: float = 1.5, timeout_s: float = 60.0) -> None:
    """Wait until no new frame came for ``quiet_s`` (the still PNG has arrived)."""
    end = time.monotonic() + timeout_s
    last, t = frames(page), time.monotonic()
    while time.monotonic() < end:
        time.sleep(0.25)
        n = frames(page)
        if n != last:
            last, t = n, time.monotonic()
        elif time.monotonic() - t >= quiet_s:
            return


def test_page_shows_the_cloud_and_a_drag_turns_it(browser, pipe, tmp_path):
    page = _open(browser, pipe)
    _settle(page)
    before = canvas_pixels(page)
    page.screenshot(path=str(tmp_path / "page.png"))
    assert _lit(before) > 500, "the cloud is not in the picture"
    n0 = frames(page)
    box = page.locator("#view").bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    for i in range(1, 11):
        page.mouse.move(x + 12 * i, y + 4 * i)
        time.sleep(0.03)
    page.mouse.up()
    wait_frames(page, n0 + 1)
    _settle(page)
    after = canvas_pixels(page)
    changed = (np.abs(after.astype(int) - before.astype(int)).max(axis=2) > 40).mean()
    assert changed > 0.01, f"the drag did not change the picture ({changed:.4f} of the pixels)"
    assert page.evaluate("document.getElementById('view').dataset.mime") == "image/png"  # still: lossless
    st = page.evaluate("window.pointflowView.state()")
    assert st is not None and st["camera"]["mode"] == "fixed"  # the orbit reached the render stage
    assert not page.errors, page.errors
    page.context.close()


def test_click_on_the_known_point_shows_its_coordinates(browser, pipe):
    page = _open(browser, pipe)
    # a camera looking straight down on the known point: it is in the middle of the picture
    _camera(page, eye=[KNOWN[0], KNOWN[1], 30.0], target=list(KNOWN), up=[0.0, 1.0, 0.0])
    _settle(page)
    box = page.locator("#view").bounding_box()
    hit = None
    # the point is drawn 3 px wide: try the centre and its neighbours (CSS px = frame px here)
    for dx, dy in ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (1, 1)):
        page.mouse.click(box["x"] + box["width"] / 2 + dx, box["y"] + box["height"] / 2 + dy)
        page.wait_for_function("window.pointflowView.lastPick !== null", timeout=30000)
        pick = page.evaluate("window.pointflowView.lastPick")
        if pick["point"] is not None:
            hit = pick
            break
        page.evaluate("window.pointflowView.lastPick = null")
    assert hit is not None, "no point under the click"
    assert np.allclose(hit["point"]["position"], KNOWN, atol=1e-4)
    text = page.locator("#info").inner_text()
    assert "1.500" in text and "-2.250" in text and "3.000" in text, text
    # georeferenced values in full, to the mm (they were shown as 6.366e+5: about 50 ft)
    shown = page.evaluate("[636612.34567, -8.5e5, 1e-5, 1.5e13].map(window.pointflowView.fmtFull)")
    assert shown == ["636612.346", "-850000.000", "1.000000e-5", "1.500000000e+13"], shown
    # lengths and the legend in the frame's units (a map in feet is labelled in feet)
    lens = page.evaluate("[[1500, 'm'], [200, 'm'], [0.25, undefined], [200, 'ft'], [1500, 'US ft'], [3, '']]"
                         ".map(([x, u]) => pointflowOverlay.fmtLen(x, u))")
    assert lens == ["1.5 km", "200 m", "25 cm", "200 ft", "1500 US ft", "3"], lens
    titles = page.evaluate("[{color_by: 'z', colormap: 'turbo', auto: true, unit: 'ft'},"
                           " {color_by: 'z', colormap: 'turbo', auto: false},"
                           " {color_by: 'intensity', colormap: 'viridis', auto: true, unit: ''}]"
                           ".map(pointflowOverlay.legendTitle)")
    assert titles == ["z (ft) · turbo · auto range", "z (m) · turbo", "intensity · viridis · auto range"], titles
    assert page.evaluate("window.pointflowView.units()") == {"xy": "m", "z": "m"}, "live points alone: metres"
    # legend ticks with the decimals their range needs (3 always: "406.260 450.000" ran together)
    ticks = page.evaluate("[[406.26, 114.25], [450, 114.25], [0.5, 1], [12.5, 0.01], [6400, 6400], [2e7, 1e7]]"
                          ".map(([v, r]) => pointflowOverlay.fmtTick(v, r))")
    assert ticks == ["406.3", "450.0", "0.500", "12.500", "6400", "2.000e+7"], ticks
    lo = page.locator("#legend_ticks span.lo").inner_text()
    assert "." not in lo, f"intensity 0..6400: whole numbers ({lo!r})"
    # two clicks measure: the same point twice is a distance of 0
    page.select_option("#mode", "measure")
    c = (box["x"] + box["width"] / 2 + dx, box["y"] + box["height"] / 2 + dy)
    for _ in range(2):
        page.evaluate("window.pointflowView.lastPick = null")
        page.mouse.click(*c)
        page.wait_for_function("window.pointflowView.lastPick !== null", timeout=30000)
    assert "distance 0.000" in page.locator("#info").inner_text()
    page.context.close()
    # a phone: a tap picks too
    phone = _open(browser, pipe, touch=True)
    _camera(phone, eye=[KNOWN[0], KNOWN[1], 30.0], target=list(KNOWN), up=[0.0, 1.0, 0.0])
    _settle(phone)
    pbox = phone.locator("#view").bounding_box()
    phone.evaluate("window.pointflowView.lastPick = null")
    phone.touchscreen.tap(pbox["x"] + pbox["width"] / 2 + dx, pbox["y"] + pbox["height"] / 2 + dy)
    phone.wait_for_function("window.pointflowView.lastPick !== null", timeout=30000)
    tapped = phone.evaluate("window.pointflowView.lastPick")
    assert tapped["point"] is not None and np.allclose(tapped["point"]["position"], KNOWN, atol=1e-4)
    phone.context.close()


def _camera(page, **cam):
    """Send a camera message as the page does (through its WebSocket)."""
    import json

    page.evaluate(f"window.pointflowView.control({json.dumps({'cmd': 'camera', **cam})})")


def test_two_tabs_keep_their_own_cameras(browser, pipe):
    a, b = _open(browser, pipe), _open(browser, pipe)
    _camera(a, eye=[0.0, 0.0, 40.0], target=[0.0, 0.0, 0.0], up=[0.0, 1.0, 0.0])
    _camera(b, eye=[40.0, 0.0, 5.0], target=[0.0, 0.0, 0.0], up=[0.0, 0.0, 1.0])
    for p in (a, b):
        _settle(p)
    sa, sb = (p.evaluate("window.pointflowView.state()") for p in (a, b))
    assert np.allclose(sa["camera"]["eye"], [0, 0, 40]) and np.allclose(sb["camera"]["eye"], [40, 0, 5])
    ia, ib = canvas_pixels(a), canvas_pixels(b)
    assert _lit(ia) > 500 and _lit(ib) > 100
    diff = (np.abs(ia.astype(int) - ib.astype(int)).max(axis=2) > 40).mean()
    assert diff > 0.05, "the two tabs show the same picture"
    pipe.wait(10, until=lambda: len(serve_stats(pipe).get("views", {})) >= 2)  # counts come with heartbeats
    st = serve_stats(pipe)
    assert st["clients"] >= 2
    per_view = list(st["views"].values())
    assert len(per_view) >= 2 and all(v["frames"] > 0 and v["bytes_per_frame"] > 0 for v in per_view), per_view
    assert st["png_bytes_mean"] > 0 and st["encode_ms_mean"] > 0
    # the page's stats line: points, frames/s, drops, sources
    page_stats = a.locator("#stats")
    a.wait_for_function("document.getElementById('stats').textContent.includes('points 6401')", timeout=30000)
    assert "drops" in page_stats.inner_text() and "source: scene" in page_stats.inner_text()
    for p in (a, b):
        p.context.close()


def _scans(path: str, n: int) -> str:
    d = os.path.join(path, "scans")
    os.makedirs(d, exist_ok=True)
    for i in range(n):
        g = np.arange(200, dtype=float)
        np.savez(os.path.join(d, f"s{i:03d}.npz"), x=np.full(200, float(i)), y=g / 20, z=np.sin(g / 10),
                 intensity=np.full(200, float(i), np.float32))
    return d


def test_timeline_pauses_and_seeks_a_replay(browser, tmp_path):
    n, rate = 40, 10.0  # 4 s of recording, looped
    src = {"transport": "file", "name": "rec", "options": {"path": _scans(str(tmp_path), n), "rate": rate}}
    with Pipeline.from_dict(config(src, playback={"loop": True}), out_dir=str(tmp_path)) as pipe:
        page = _open(browser, pipe)
        assert page.locator("#timeline").is_visible()
        page.wait_for_function("window.pointflowView.playback() !== null", timeout=30000)
        assert page.evaluate("window.pointflowView.playback().paused") is False
        page.click("#play")  # pause
        page.wait_for_function("window.pointflowView.playback() && window.pointflowView.playback().paused",
                               timeout=30000)
        st = pipe.playback()["rec"]
        assert st["paused"]
        pipe.wait(0.5)
        src_in = pipe.stats()["stages"]["rec"]["points_out"]
        pipe.wait(1.5)
        assert pipe.stats()["stages"]["rec"]["points_out"] == src_in, "the paused replay still sends"
        # seek to the middle with the slider (as a user's drag ends: a change event)
        page.evaluate("""() => { const s = document.getElementById('seek'); s.value = '500';
                                 s.dispatchEvent(new Event('change')); }""")
        pipe.wait(20, until=lambda: pipe.playback()["rec"]["seeks"] >= 1)
        st = pipe.playback()["rec"]
        assert st["seeks"] >= 1 and st["paused"]
        index0 = st["index"]
        page.click("#play")  # play: the replay goes on from the middle
        pipe.wait(30, until=lambda: pipe.playback()["rec"]["index"] != index0)
        st = pipe.playback()["rec"]
        assert not st["paused"]
        assert n // 2 - 1 <= st["index"] <= n - 1 and st["position_s"] >= 0.45 * st["duration_s"], st
        page.context.close()


def test_keyboard_and_style_controls(browser, pipe):
    page = _open(browser, pipe)
    _settle(page)
    page.locator("#view").focus()
    v0 = page.evaluate("window.pointflowView.state().version")
    page.keyboard.press("ArrowLeft")  # orbit
    page.wait_for_function(f"window.pointflowView.state().version > {v0}", timeout=30000)
    assert page.evaluate("window.pointflowView.state().camera.mode") == "fixed"
    page.keyboard.press("f")  # fit: the camera follows the data again
    page.wait_for_function("window.pointflowView.state().camera.mode === 'auto'", timeout=30000)
    _settle(page)
    before = canvas_pixels(page)
    page.select_option("#colormap", "grayscale")
    page.wait_for_function("window.pointflowView.state().style.colormap === 'grayscale'", timeout=30000)
    _settle(page)
    after = canvas_pixels(page)
    lit = after.max(axis=2) > 60
    assert lit.sum() > 500
    # grayscale: the lit pixels are grey (r = g = b within JPEG/PNG rounding); turbo's were not
    spread = (after.max(axis=2).astype(int) - after.min(axis=2))[lit]
    assert np.median(spread) <= 6, np.median(spread)
    assert (np.abs(after.astype(int) - before.astype(int)).max(axis=2) > 40).mean() > 0.01
    page.select_option("#colormap", "turbo")  # the style is the pipeline's: put it back for the others
    page.wait_for_function("window.pointflowView.state().style.colormap === 'turbo'", timeout=30000)
    page.context.close()
