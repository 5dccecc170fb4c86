"""The page over a slow link (issue 39), in headless Chromium: dragged over a 1 Mbit/s,
40 ms relay (pointflow/testing/linksim.py) it gets frames sent reduced and draws them at the
view's size; when the drag stops the lossless still (PNG, full size) replaces them."""
from __future__ import annotations

import time

import pytest

from pointflow.testing.linksim import SlowLink

from .browser import new_page, wait_frames
from .helpers import scene_pipeline, TOKEN, base_url


@pytest.fixture(scope="module")
def pipe(tmp_path_factory):
    d = tmp_path_factory.mktemp("link_browser")
    with scene_pipeline(str(d), adapt_fps=20) as p:
        yield p


def _canvas(page) -> dict:
    """The canvas's size, the view's (its last reply's), what the last frame was."""
    return page.evaluate("(() => { const c = document.getElementById('view');"
                         " const s = window.pointflowView.state();"
                         " return {w: c.width, h: c.height, vw: s && s.width, vh: s && s.height,"
                         " mime: c.dataset.mime, reduce: c.dataset.reduce}; })()")


def test_a_page_dragged_over_a_slow_link_draws_reduced_frames_at_its_size(browser, pipe):
    port = int(base_url(pipe).rsplit(":", 1)[1])
    with SlowLink(port, 1e6, 0.040) as link:
        page = new_page(browser)
        try:
            page.goto(f"http://127.0.0.1:{link.port}/?token={TOKEN}")
            wait_frames(page, 1)
            box = page.locator("#view").bounding_box()
            x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
            page.mouse.move(x, y)
            page.mouse.down()
            reduced = None
            end = time.monotonic() + 120
            i = 0
            seen = []
            # drag to and fro until a frame comes reduced (half or a quarter of the view's side)
            # and is drawn at the view's size (the page may still be settling its own size:
            # a frame of the size before a resize is not one to judge)
            while reduced is None and time.monotonic() < end:
                i += 1
                page.mouse.move(x + 60 * ((i // 20) % 2 * 2 - 1) * (i % 20) / 20, y)
                time.sleep(0.03)
                c = _canvas(page)
                if c["reduce"] not in (None, "1"):
                    seen.append(c)
                    if (c["w"], c["h"]) == (c["vw"], c["vh"]):
                        reduced = c
            page.mouse.up()
            assert reduced is not None, f"no reduced frame drawn at the view's size over 1 Mbit/s: {seen[-5:]}"
            assert reduced["mime"] == "image/jpeg"
            # the still: lossless, full size, at the view's size
            page.wait_for_function("(() => { const c = document.getElementById('view');"
                                   " const s = window.pointflowView.state();"
                                   " return c.dataset.mime === 'image/png' && c.dataset.reduce === '1' && s"
                                   " && c.width === s.width && c.height === s.height; })()", timeout=90000)
            assert not page.errors, page.errors
        finally:
            page.context.close()
