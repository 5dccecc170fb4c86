"""The page over a slow link (issue 39), in headless Chromium: dragged over a 1 Mbit/s,
40 ms relay (pointflow/serve/linksim.py) it gets frames sent reduced and draws them at the
view's size; when the drag stops the lossless still (PNG, full size) replaces them."""
from __future__ import annotations

import time

import pytest

from pointflow import Pipeline
from pointflow.serve.linksim import SlowLink

from .browser import launch, need_browser, new_page, wait_frames
from .helpers import TOKEN, base_url, config, file_source, scene


@pytest.fixture(scope="module")
def browser():
    sync_api = need_browser()
    with sync_api.sync_playwright() as pw:
        b = launch(pw)
        yield b
        b.close()


@pytest.fixture(scope="module")
def pipe(tmp_path_factory):
    d = tmp_path_factory.mktemp("link_browser")
    with Pipeline.from_dict(config(file_source(scene(str(d))), serve={"adapt_fps": 20}), out_dir=str(d)) as p:
        p.wait(90, until=lambda: p.stats()["stages"]["render"]["points_in"] >= 6401)
        base_url(p)
        yield p


def _canvas(page) -> dict:
    return page.evaluate("(() => { const c = document.getElementById('view'); const r = c.getBoundingClientRect();"
                         " return {w: c.width, h: c.height, cw: Math.round(r.width), ch: Math.round(r.height),"
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
            while reduced is None and time.monotonic() < end:  # drag to and fro until a frame comes reduced
                i += 1
                page.mouse.move(x + 60 * ((i // 20) % 2 * 2 - 1) * (i % 20) / 20, y)
                time.sleep(0.03)
                c = _canvas(page)
                if c["reduce"] not in (None, "1"):
                    reduced = c
            page.mouse.up()
            assert reduced is not None, "no frame came reduced while dragging over 1 Mbit/s"
            # a reduced frame is drawn at the view's size, not its own
            assert (reduced["w"], reduced["h"]) == (reduced["cw"], reduced["ch"]), reduced
            assert reduced["mime"] == "image/jpeg"
            page.wait_for_function("document.getElementById('view').dataset.mime === 'image/png'", timeout=90000)
            still = _canvas(page)
            assert still["reduce"] == "1" and (still["w"], still["h"]) == (still["cw"], still["ch"]), still
            assert not page.errors, page.errors
        finally:
            page.context.close()
