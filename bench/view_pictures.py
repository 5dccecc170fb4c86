"""Screenshots of the browser page for docs/views.md: a small terrain (a file replay of
one 40k-point scan, coloured by z) in the real page, in headless Chromium: axes, ground
grid, compass and colour legend (docs/img/view_overlay.png), a measurement between two
picked points (docs/img/view_measure.png) and the help overlay (docs/img/view_help.png).

    .venv/bin/python bench/view_pictures.py      # ~30 s on 2 cores
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
import time

import numpy as np

import _harness
from pointflow import Pipeline

OUT = _harness.ROOT / "docs" / "img"
TOKEN = "pictures-token-0123456789"


def terrain(path: str) -> str:
    g = np.stack(np.meshgrid(np.linspace(-12, 12, 200), np.linspace(-8, 8, 200)), -1).reshape(-1, 2)
    z = 1.2 * np.sin(g[:, 0] / 3.0) * np.cos(g[:, 1] / 2.5) + 0.04 * g[:, 0] + 1.0
    f = os.path.join(path, "terrain.npz")
    np.savez(f, x=g[:, 0], y=g[:, 1], z=z, intensity=np.hypot(g[:, 0], g[:, 1]).astype(np.float32))
    return f


def main() -> None:
    from playwright.sync_api import sync_playwright

    d = tempfile.mkdtemp(prefix="pf-pictures-")
    cfg = {"source": {"transport": "file", "name": "terrain", "options": {"path": terrain(d), "realtime": False}},
           "ring": {"max_points": 60000}, "cadence": {"target_hz": 20},
           "render": {"backend": "cpu", "size": [320, 240], "point_size": 3, "color_by": "z",
                      "output": {"every_n_frames": 100000}},
           "serve": {"port": 0, "token": TOKEN}}
    try:
        with Pipeline.from_dict(cfg, out_dir=d) as p:
            p.wait(90, until=lambda: p.stats()["stages"]["render"]["points_in"] >= 40000)
            p.wait(60, until=lambda: p.stats()["stages"].get("serve", {}).get("port"))
            port = p.stats()["stages"]["serve"]["port"]
            with sync_playwright() as pw:
                b = pw.chromium.launch(executable_path=shutil.which("chromium") or "/usr/bin/chromium", headless=True,
                                       args=["--no-sandbox", "--disable-gpu"])
                page = b.new_context(viewport={"width": 960, "height": 600}, device_scale_factor=1,
                                     bypass_csp=True).new_page()
                page.goto(f"http://127.0.0.1:{port}/?token={TOKEN}")
                page.wait_for_function("window.pointflowView && window.pointflowView.frames() > 0", timeout=90000)
                cam = {"cmd": "camera", "eye": [17.0, -19.0, 13.0], "target": [0.0, 0.0, 0.0], "up": [0, 0, 1]}
                page.evaluate(f"window.pointflowView.control({json.dumps(cam)})")
                page.wait_for_function("window.pointflowView.camera() && window.pointflowView.camera().eye[0] === 17",
                                       timeout=60000)
                time.sleep(2.0)
                page.screenshot(path=str(OUT / "view_overlay.png"))
                box = page.locator("#view").bounding_box()
                page.select_option("#mode", "measure")
                for fx, fy in ((0.47, 0.58), (0.64, 0.47)):
                    page.evaluate("window.pointflowView.lastPick = null")
                    page.mouse.click(box["x"] + fx * box["width"], box["y"] + fy * box["height"])
                    page.wait_for_function("window.pointflowView.lastPick !== null", timeout=30000)
                time.sleep(1.0)
                page.screenshot(path=str(OUT / "view_measure.png"))
                page.select_option("#mode", "pick")
                page.locator("#view").focus()
                page.keyboard.press("?")
                time.sleep(0.3)
                page.screenshot(path=str(OUT / "view_help.png"))
                b.close()
    finally:
        shutil.rmtree(d, ignore_errors=True)
    print("wrote", ", ".join(str(OUT / n) for n in ("view_overlay.png", "view_measure.png", "view_help.png")))


if __name__ == "__main__":
    main()
