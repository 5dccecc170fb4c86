"""The notebook widget's controls in a real JupyterLab and a real Chromium (issue 39, item 6):
the controls carry labels; Reset brings a turned view back to the picture it started with;
measure joins two picked points and shows their distance; a replay gets a timeline whose
Step and seek (while paused) change the message shown; after ``p.stop()`` the cell shows one
line and the widget says "run ended" with its controls off. And the widget renders a frame
in classic Notebook 7 too.

One JupyterLab session runs all the control checks (its start costs 30-60 s on 2 busy
cores); every wait is on a condition (a frame number, a data attribute), none is timed."""
from __future__ import annotations

import time

import pytest

from .helpers import (REPO, browser_page, changed, jupyter, lit, need, open_notebook, pixels, run_cell, wait_widget,
                      write_notebook)

#: 10 scans, 2 a second (message i at i / 2 s): a tilted plane, scan i raised by i (colour by z,
#: a fixed range: each scan has its own colours). Paused, holding at the end; the first scan sent.
REPLAY = """
import os, tempfile
import numpy as np
from pointflow import Pipeline
scans = tempfile.mkdtemp()
g = np.stack(np.meshgrid(np.linspace(-10, 10, 150), np.linspace(-5, 5, 75)), -1).reshape(-1, 2)
for i in range(10):
    np.savez(os.path.join(scans, f"s{i:03d}.npz"), x=g[:, 0], y=g[:, 1], z=0.3 * g[:, 0] + i)
p = Pipeline.from_dict({"name": "nb", "source": {"transport": "file", "name": "rec", "options": {"path": scans, "rate": 2}},
                        "playback": {"paused": True, "hold": True},
                        "ring": {"max_points": 12000}, "cadence": {"target_hz": 30}, "tracing": {"enabled": False},
                        "render": {"backend": "cpu", "size": [320, 240], "point_size": 3, "color_by": "z",
                                   "color_range": [-3, 13], "output": {"dir": None}}}, out_dir="")
p.start()
p.playback(step=1)
p.wait(60, until=lambda: p.stats()["stages"]["render"].get("drawn_count", 0) >= len(g))
p.show(width=320, height=240)
"""
STOP = "p.stop()"


#: The page's overlay (axes, grid, compass, marks) and the frames' camera and legend (issue 39,
#: items 1-3, another branch): where they are, the widget draws them and this test checks them.
OVERLAY = (REPO / "pointflow" / "serve" / "static" / "overlay.js").exists()
#: Pixels of the widget's overlay canvas that something was drawn on (its own, not the picture's).
DRAWN = "c => { const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; let n = 0; " \
        "for (let i = 3; i < d.length; i += 4) if (d[i] > 0) n++; return n; }"


def _attr(page, selector: str, name: str):
    return page.eval_on_selector(selector, f"e => e.dataset.{name} ?? null")


def _wait_attr(page, selector: str, js_cond: str, timeout: float = 60000) -> None:
    page.wait_for_function(f"() => {{ const e = document.querySelector({selector!r}); return !!e && ({js_cond}); }}",
                           timeout=timeout)


def _still(page, canvas, after_version: int):
    """The picture once a still (PNG) frame at a view version past ``after_version`` is drawn."""
    _wait_attr(page, "canvas.pf-canvas", f"Number(e.dataset.version) > {after_version} && e.dataset.mime === 'image/png'")
    return pixels(canvas)


def _drag(page, canvas) -> None:
    box = canvas.bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    for i in range(1, 11):
        page.mouse.move(x + 10 * i, y + 5 * i)
        time.sleep(0.03)
    page.mouse.up()


def test_widget_controls_in_jupyterlab(tmp_path):
    sync_api = need("lab")
    with jupyter(tmp_path, "lab") as (url, token, d, page_path), browser_page(sync_api) as page:
        write_notebook(d / "controls.ipynb", REPLAY, STOP)
        open_notebook(page, url, token, page_path, "controls.ipynb")
        run_cell(page, 0)
        canvas = wait_widget(page, d)
        view = ".pointflow-view"

        # labelled controls
        labels = page.locator(f"{view} .pf-label").all_inner_texts()
        for name in ("Click", "Colour", "Map", "Size", "EDL", "Time", "Speed", "Loop"):
            assert name in labels, labels
        assert page.locator(f"{view} button", has_text="Reset").count() == 1
        # the size slider's value, once the view's first state has come (shown as "… px" before it)
        _wait_attr(page, ".pointflow-view", "e.dataset.state === '1'")
        assert page.locator(f"{view} .pf-value").inner_text().strip() == "3 px"

        # axes, grid, compass and the legend over the picture, each switched off by its box
        if OVERLAY:
            _wait_attr(page, "canvas.pf-canvas", "e.dataset.overlay === '1'")
            legend = page.locator(f"{view} .pf-legend")
            legend.wait_for(timeout=60000)
            assert float(legend.get_attribute("data-lo")) == -3 and float(legend.get_attribute("data-hi")) == 13
            assert legend.get_attribute("data-colormap") == "turbo"
            assert page.locator(f"{view} .pf-legend-title").inner_text().startswith("z (m) · turbo")
            assert page.eval_on_selector(f"{view} canvas.pf-marks", DRAWN) > 500, "no axes or grid drawn"
            for k in ("axes", "grid", "compass", "legend"):
                page.locator(f"{view} input.pf-show-{k}").uncheck()
            assert page.eval_on_selector(f"{view} canvas.pf-marks", DRAWN) == 0
            assert not legend.is_visible()
            for k in ("axes", "grid", "compass", "legend"):
                page.locator(f"{view} input.pf-show-{k}").check()
            assert page.eval_on_selector(f"{view} canvas.pf-marks", DRAWN) > 500

        # Reset: a turned view goes back to the picture it started with
        v0 = int(_attr(page, "canvas.pf-canvas", "version") or 0)
        start = _still(page, canvas, v0 - 1)
        assert lit(start) > 2000, f"the cloud is not in the picture ({lit(start)} lit pixels)"
        _drag(page, canvas)
        turned = _still(page, canvas, v0)
        assert changed(turned, start) > 0.02, "the drag did not turn the view"
        v1 = int(_attr(page, "canvas.pf-canvas", "version"))
        page.locator(f"{view} button", has_text="Reset").click()
        back = _still(page, canvas, v1)
        assert changed(back, start) < 0.01, f"Reset did not bring the view back ({changed(back, start):.1%} differ)"

        # measure: two clicks on the cloud, their distance shown and drawn
        page.select_option(f"{view} select.pf-mode", "measure")
        box = canvas.bounding_box()
        cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
        page.mouse.click(cx - 40, cy)
        page.wait_for_function("() => document.querySelector('.pointflow-view .pf-info').textContent.includes('first point')",
                               timeout=60000)
        page.mouse.click(cx + 40, cy)
        _wait_attr(page, "canvas.pf-canvas", "e.dataset.distance !== undefined")
        distance = float(_attr(page, "canvas.pf-canvas", "distance"))
        assert 0.5 < distance < 20, distance  # two points of the 20 m wide plane, 80 px apart
        assert f"distance {distance:.3f}" in page.locator(f"{view} .pf-info").inner_text()
        assert page.eval_on_selector(f"{view} canvas.pf-marks", DRAWN) > 50, "no measure line drawn"
        page.select_option(f"{view} select.pf-mode", "pick")  # a new mode clears the line
        _wait_attr(page, "canvas.pf-canvas", "e.dataset.distance === undefined")

        # the timeline of the replay: paused on scan 0; Step sends scan 1, a seek (paused) scan 8
        timeline = page.locator(f"{view} .pf-timeline")
        assert timeline.is_visible() and timeline.get_attribute("data-sources") == "rec"
        _wait_attr(page, ".pointflow-view .pf-timeline", "e.dataset.paused === 'true' && e.dataset.index === '0'")
        assert page.locator(f"{view} .pf-play").inner_text() == "Play"
        v2 = int(_attr(page, "canvas.pf-canvas", "version"))
        scan0 = _still(page, canvas, v2 - 1)
        page.locator(f"{view} .pf-step").click()
        _wait_attr(page, ".pointflow-view .pf-timeline", "e.dataset.index === '1'")
        page.eval_on_selector(f"{view} .pf-seek", "e => { e.value = '800'; e.dispatchEvent(new Event('change')); }")
        _wait_attr(page, ".pointflow-view .pf-timeline", "e.dataset.index === '8' && e.dataset.paused === 'true'")
        assert float(_attr(page, ".pointflow-view .pf-timeline", "position")) == pytest.approx(4.0)
        end = time.monotonic() + 60
        while changed(pixels(canvas), scan0) < 0.02 and time.monotonic() < end:  # scan 8's colours arrive
            time.sleep(0.25)
        assert changed(pixels(canvas), scan0) >= 0.02, "the seek while paused did not change the picture"

        # p.stop(): one line in the cell, "run ended" in the widget, its controls off
        run_cell(page, 1)
        out = page.locator(".jp-Notebook .jp-Cell").nth(1).locator(".jp-OutputArea-executeResult")  # the value, not logs
        out.first.wait_for(timeout=120000)
        text = out.first.locator(".jp-OutputArea-output").inner_text()
        assert text.startswith("Stopped(frames=") and "\n" not in text.strip(), text
        page.locator(f"{view} .pf-ended", has_text="run ended").wait_for(timeout=60000)
        assert _attr(page, "canvas.pf-canvas", "stopped") == "run ended"
        disabled = page.eval_on_selector_all(f"{view} button, {view} select, {view} input", "es => es.map(e => e.disabled)")
        assert disabled and all(disabled), disabled
        page.screenshot(path=str(d / "stopped.png"))


NOTEBOOK7 = """
import numpy as np
from pointflow import Pipeline
p = Pipeline.from_dict({"name": "nb", "sources": [{"transport": "api", "name": "api"}],
                        "ring": {"max_points": 50000}, "tracing": {"enabled": False},
                        "render": {"backend": "cpu", "size": [320, 240], "point_size": 3, "color_by": "z",
                                   "output": {"dir": None}}}, out_dir="")
p.start()
g = np.stack(np.meshgrid(np.linspace(-10, 10, 150), np.linspace(-5, 5, 75)), -1).reshape(-1, 2)
p.send(np.column_stack([g, 0.3 * g[:, 0]]).astype(np.float32))
p.wait(60, until=lambda: p.stats()["stages"]["render"].get("drawn_count", 0) >= len(g))
p.show(width=320, height=240)
"""


def test_widget_renders_in_classic_notebook_7(tmp_path):
    sync_api = need("notebook")
    with jupyter(tmp_path, "notebook") as (url, token, d, page_path), browser_page(sync_api, "notebook") as page:
        write_notebook(d / "nb7.ipynb", NOTEBOOK7)
        open_notebook(page, url, token, page_path, "nb7.ipynb")
        run_cell(page, 0)
        canvas = wait_widget(page, d)
        picture = _still(page, canvas, -1)
        assert lit(picture) > 2000, f"the cloud is not in the widget's picture ({lit(picture)} lit pixels)"
        assert page.locator(".pointflow-view .pf-label", has_text="Colour").count() == 1
