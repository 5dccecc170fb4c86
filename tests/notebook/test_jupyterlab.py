"""The notebook view in a real JupyterLab server and a real browser (Debian's chromium,
headless, driven by playwright): a notebook starts a pipeline and shows ``p.show()``; the
widget shows the live picture, and a drag on it turns the view.

Cost here (2 busy cores): 30-60 s, most of it JupyterLab's start, the kernel's and the
pipeline's. Under CI (``CI=true``) a missing browser, playwright or JupyterLab fails the
test instead of skipping it."""
from __future__ import annotations

import io
import json
import os
import secrets
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
CHROMIUM = os.environ.get("POINTFLOW_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"

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


def _need():
    why = None
    try:
        from playwright import sync_api
    except ImportError:
        sync_api, why = None, "playwright is not installed (pip install 'pointflow[test]')"
    if why is None and not os.path.exists(CHROMIUM):
        why = f"no chromium at {CHROMIUM} (scripts/install-system-deps.sh installs it)"
    if why is None and shutil.which("jupyter-lab", path=os.path.dirname(sys.executable)) is None:
        why = "JupyterLab is not installed (pip install 'pointflow[test]')"
    if why is None:
        try:
            import anywidget  # noqa: F401
        except ImportError:
            why = "anywidget is not installed (pip install 'pointflow[notebook]')"
    if why is not None:
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(why + " -- the notebook test must run in CI")
        pytest.skip(why)
    return sync_api


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _notebook(path: Path) -> None:
    nb = {"cells": [{"cell_type": "code", "execution_count": None, "id": "live", "metadata": {}, "outputs": [],
                     "source": CELL.strip()}],
          "metadata": {"kernelspec": {"display_name": "Python 3", "language": "python", "name": "python3"}},
          "nbformat": 4, "nbformat_minor": 5}
    path.write_text(json.dumps(nb))


@pytest.fixture
def lab(tmp_path):
    """A JupyterLab server on a free loopback port with a token, in its own directories."""
    port, token = _free_port(), secrets.token_hex(16)
    home = tmp_path / "home"
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""),
               HOME=str(home), JUPYTER_CONFIG_DIR=str(home / "config"), JUPYTER_RUNTIME_DIR=str(home / "runtime"),
               JUPYTERLAB_WORKSPACES_DIR=str(home / "workspaces"), JUPYTERLAB_SETTINGS_DIR=str(home / "settings"))
    env.pop("DISPLAY", None)
    env.pop("WAYLAND_DISPLAY", None)
    log = open(tmp_path / "lab.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "jupyterlab", "--no-browser", "--ip=127.0.0.1", f"--port={port}",
                             f"--IdentityProvider.token={token}", f"--ServerApp.root_dir={tmp_path}",
                             "--ServerApp.open_browser=False", *(["--allow-root"] if os.geteuid() == 0 else []), "--LabApp.news_url=", "--LabApp.check_for_updates_class="
                             "jupyterlab.NeverCheckForUpdate"],
                            cwd=str(tmp_path), env=env, stdout=log, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    try:
        end = time.monotonic() + 120
        while True:
            try:
                with urllib.request.urlopen(f"{url}/api/status?token={token}", timeout=2) as r:
                    if r.status == 200:
                        break
            except OSError:
                pass
            if proc.poll() is not None or time.monotonic() > end:
                log.flush()
                pytest.fail("JupyterLab did not start: " + (tmp_path / "lab.log").read_text()[-2000:])
            time.sleep(0.3)
        yield url, token, tmp_path
    finally:
        # shutting the kernels down ends their pipelines (Pipeline.stop at exit)
        try:
            req = urllib.request.Request(f"{url}/api/kernels?token={token}")
            with urllib.request.urlopen(req, timeout=5) as r:
                for k in json.loads(r.read()):
                    urllib.request.urlopen(urllib.request.Request(
                        f"{url}/api/kernels/{k['id']}?token={token}", method="DELETE"), timeout=30).read()
        except OSError:
            pass
        proc.terminate()
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()


def _pixels(locator):
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(locator.screenshot())).convert("RGB"))


def test_widget_shows_the_live_view_and_a_drag_turns_it(lab):
    sync_api = _need()
    url, token, d = lab
    _notebook(d / "view.ipynb")
    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True,
                                     args=["--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage"])
        try:
            page = browser.new_page(viewport={"width": 1200, "height": 900}, device_scale_factor=1)
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(f"{url}/lab/tree/view.ipynb?token={token}", timeout=120000)
            page.wait_for_selector(".jp-Notebook .jp-Cell .cm-content", timeout=120000)
            # the kernel is up when the toolbar's status says idle
            page.wait_for_selector(".jp-Notebook-ExecutionIndicator[data-status='idle']", timeout=120000)
            page.click(".jp-Notebook .jp-Cell .cm-content")
            page.keyboard.press("Shift+Enter")
            canvas = page.locator("canvas.pf-canvas")
            canvas.wait_for(timeout=120000)
            page.wait_for_function("() => Number(document.querySelector('canvas.pf-canvas').dataset.frames || 0) >= 1",
                                   timeout=120000)
            time.sleep(1.0)  # the still (PNG) frame after the first
            before = _pixels(canvas)
            lit = int((np.abs(before.astype(int) - before[0, 0].astype(int)).max(axis=2) > 40).sum())
            assert lit > 2000, f"the cloud is not in the widget's picture ({lit} lit pixels)"
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
            after = _pixels(canvas)
            changed = float((np.abs(after.astype(int) - before.astype(int)).max(axis=2) > 40).mean())
            assert int(canvas.get_attribute("data-frames")) > n0
            assert changed > 0.02, f"the drag did not turn the view ({changed:.1%} of pixels changed)"
            assert not errors, errors
        finally:
            browser.close()
