"""The notebook view in a real JupyterLab server and a real browser (Debian's chromium,
headless, driven by playwright): a notebook starts a pipeline and shows ``p.show()``; the
widget shows the live picture, and a drag on it turns the view.

Cost here (2 busy cores): 30-60 s, most of it JupyterLab's start, the kernel's and the
pipeline's. Under CI (``CI=true``) a missing browser, playwright or JupyterLab fails the
test instead of skipping it."""
from __future__ import annotations

import time

import pytest

from .helpers import browser_page, changed, jupyter, lit, need, open_notebook, pixels, run_cell, wait_widget, write_notebook

CELL = """
import numpy as np
from pointflow import Pipeline
p = Pipeline.from_dict({"name": "nb", "sources": [{"transport": "api", "name": "api"}],
                        "ring": {"max_points": 50000}, "cadence": {"target_hz": 30}, "tracing": {"enabled": False},
                        "render": {"backend": "cpu", "size": [320, 240], "point_size": 3, "color_by": "z",
                                   "output": {"dir": None}}}, out_dir="")
p.start()
g = np.stack(np.meshgrid(np.linspace(-10, 10, 150), np.linspace(-5, 5, 75)), -1).reshape(-1, 2)
pts = np.column_stack([g, 0.3 * g[:, 0]]).astype(np.float32)
p.send(pts)
p.wait(60, until=lambda: p.stats()["stages"]["render"].get("drawn_count", 0) >= len(pts))
w = p.show(width=320, height=240)
w
"""


@pytest.fixture
def lab(tmp_path):
    """A JupyterLab server on a free loopback port with a token, in its own directories."""
    with jupyter(tmp_path, "lab") as server:
        yield server


def test_widget_shows_the_live_view_and_a_drag_turns_it(lab):
    sync_api = need("lab")
    url, token, d, page_path = lab
    write_notebook(d / "view.ipynb", CELL)
    with browser_page(sync_api) as page:
        open_notebook(page, url, token, page_path, "view.ipynb")
        run_cell(page, 0)
        canvas = wait_widget(page, d)
        time.sleep(1.0)  # the still (PNG) frame after the first
        before = pixels(canvas)
        assert lit(before) > 2000, f"the cloud is not in the widget's picture ({lit(before)} lit pixels)"
        n0 = int(canvas.get_attribute("data-frames"))
        v0 = int(canvas.get_attribute("data-version"))
        box = canvas.bounding_box()
        x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
        page.mouse.move(x, y)
        page.mouse.down()
        for i in range(1, 11):
            page.mouse.move(x + 10 * i, y + 5 * i)
            time.sleep(0.03)
        page.mouse.up()
        page.wait_for_function(f"() => Number(document.querySelector('canvas.pf-canvas').dataset.version) > {v0}",
                               timeout=60000)
        time.sleep(1.0)
        after = pixels(canvas)
        assert int(canvas.get_attribute("data-frames")) > n0
        assert changed(after, before) > 0.02, f"the drag did not turn the view ({changed(after, before):.1%} of pixels changed)"
