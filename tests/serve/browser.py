"""Debian's chromium, headless, driven by playwright (``executable_path``: playwright's own
browser download is never used). Under CI (``CI=true``) a missing browser fails the tests
instead of skipping them."""
from __future__ import annotations

import os
import shutil

import pytest

CHROMIUM = os.environ.get("POINTFLOW_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"


def need_browser():
    """The sync playwright module, or a skip (a failure under CI)."""
    why = None
    try:
        from playwright import sync_api
    except ImportError:
        why = "playwright is not installed (pip install 'pointflow[test]')"
    if why is None and not os.path.exists(CHROMIUM):
        why = f"no chromium at {CHROMIUM} (scripts/install-system-deps.sh installs it)"
    if why is not None:
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(why + " -- the browser tests must run in CI")
        pytest.skip(why)
    return sync_api


def launch(pw):
    return pw.chromium.launch(executable_path=CHROMIUM, headless=True,
                              args=["--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage"])


def new_page(browser, w: int = 640, h: int = 520, touch: bool = False):
    # bypass_csp: the page's own CSP forbids eval, which playwright's wait_for_function uses
    ctx = browser.new_context(viewport={"width": w, "height": h}, bypass_csp=True, device_scale_factor=1,
                              has_touch=touch)
    page = ctx.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.errors = errors
    return page


def frames(page) -> int:
    return page.evaluate("window.pointflowView ? window.pointflowView.frames() : 0")


def wait_frames(page, n: int, timeout_ms: int = 90000) -> None:
    page.wait_for_function(f"window.pointflowView && window.pointflowView.frames() >= {n}", timeout=timeout_ms)


def canvas_pixels(page):
    """The canvas's picture as an (h, w, 3) array (a screenshot of the element)."""
    import io

    import numpy as np
    from PIL import Image

    png = page.locator("#view").screenshot()
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))
