"""A real Jupyter server (JupyterLab or classic Notebook 7) and a real headless Chromium for the
notebook view's tests: start the server on a free loopback port with a token, in its own
directories; open a notebook; run its cells as a user does (Ctrl+Enter in the cell)."""
from __future__ import annotations

import contextlib
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
#: The server apps: module to run, the script that says it is installed, the page of a notebook.
APPS = {"lab": ("jupyterlab", "jupyter-lab", "lab/tree"), "notebook": ("notebook", "jupyter-notebook", "notebooks")}


def need(app: str = "lab"):
    """playwright's sync API, or a skip (a failure under ``CI=true``) naming what is missing."""
    why = None
    try:
        from playwright import sync_api
    except ImportError:
        sync_api, why = None, "playwright is not installed (pip install 'pointflow[test]')"
    if why is None and not os.path.exists(CHROMIUM):
        why = f"no chromium at {CHROMIUM} (scripts/install-system-deps.sh installs it)"
    module, script, _ = APPS[app]
    if why is None and shutil.which(script, path=os.path.dirname(sys.executable)) is None:
        why = f"{module} is not installed (pip install 'pointflow[test]')"
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


def write_notebook(path: Path, *cells: str) -> None:
    nb = {"cells": [{"cell_type": "code", "execution_count": None, "id": f"c{i}", "metadata": {}, "outputs": [],
                     "source": c.strip()} for i, c in enumerate(cells)],
          "metadata": {"kernelspec": {"display_name": "Python 3", "language": "python", "name": "python3"}},
          "nbformat": 4, "nbformat_minor": 5}
    path.write_text(json.dumps(nb))


@contextlib.contextmanager
def jupyter(tmp_path: Path, app: str = "lab"):
    """A Jupyter server (``app``: "lab" or "notebook"); yields (base url, token, root dir, page path)."""
    module, _, page_path = APPS[app]
    port, token = _free_port(), secrets.token_hex(16)
    home = tmp_path / "home"
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""),
               HOME=str(home), JUPYTER_CONFIG_DIR=str(home / "config"), JUPYTER_RUNTIME_DIR=str(home / "runtime"),
               JUPYTERLAB_WORKSPACES_DIR=str(home / "workspaces"), JUPYTERLAB_SETTINGS_DIR=str(home / "settings"))
    env.pop("DISPLAY", None)
    env.pop("WAYLAND_DISPLAY", None)
    extra = ["--LabApp.news_url=", "--LabApp.check_for_updates_class=jupyterlab.NeverCheckForUpdate"] if app == "lab" else []
    log = open(tmp_path / f"{app}.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", module, "--no-browser", "--ip=127.0.0.1", f"--port={port}",
                             f"--IdentityProvider.token={token}", f"--ServerApp.root_dir={tmp_path}",
                             "--ServerApp.open_browser=False", *(["--allow-root"] if os.geteuid() == 0 else []), *extra],
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
                pytest.fail(f"{module} did not start: " + (tmp_path / f"{app}.log").read_text()[-2000:])
            time.sleep(0.3)
        yield url, token, tmp_path, page_path
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


#: Page errors of the Jupyter front ends themselves, not of the widget: (app, where the error
#: is thrown). Notebook 7.6 throws "Cannot read properties of undefined (reading 'schema')"
#: from its own core bundle while loading the settings of a fresh user directory, with no
#: widget on the page (an empty notebook does it too).
APP_ERRORS = {"notebook": ("/static/notebook/notebook_core.",)}


def _first_frame(stack: str) -> str:
    return next((line for line in (stack or "").splitlines() if line.strip().startswith("at ")), "")


@contextlib.contextmanager
def browser_page(sync_api, app: str = "lab"):
    """A headless Chromium page (1200x900); fails the test on any page error when it ends
    (but the front end's own, :data:`APP_ERRORS`)."""
    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True,
                                     args=["--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage"])
        try:
            page = browser.new_page(viewport={"width": 1200, "height": 900}, device_scale_factor=1)
            errors: list[str] = []
            known = APP_ERRORS.get(app, ())
            page.on("pageerror", lambda e: None if any(k in _first_frame(e.stack) for k in known)
                    else errors.append(f"{e}\n{e.stack}"))
            yield page
            assert not errors, errors
        finally:
            browser.close()


def open_notebook(page, url: str, token: str, page_path: str, name: str) -> None:
    page.goto(f"{url}/{page_path}/{name}?token={token}", timeout=120000)
    page.wait_for_selector(".jp-Notebook .jp-Cell .cm-content", timeout=120000)
    # the kernel is up when the toolbar's status says idle (JupyterLab; Notebook 7 has no such
    # indicator by default: the cell is run again below until its prompt moves)
    with contextlib.suppress(Exception):
        page.wait_for_selector(".jp-Notebook-ExecutionIndicator[data-status='idle']", timeout=60000)


def dismiss_dialogs(page) -> list[str]:
    """Answer the front end's own modal dialogs with their default button (on a busy machine
    Notebook 7 can ask which kernel to start when its kernel list came after the notebook:
    the default is the notebook's own, Python 3); their texts are returned and printed, so a
    failure shows what was asked."""
    said = []
    dialogs = page.locator(".jp-Dialog")
    for _ in range(4):
        if not dialogs.count() or not dialogs.first.is_visible():
            break
        said.append(dialogs.first.inner_text().strip())
        accept = dialogs.first.locator("button.jp-mod-accept")
        if accept.count():
            accept.first.click()
        else:
            page.keyboard.press("Escape")
        with contextlib.suppress(Exception):
            dialogs.first.wait_for(state="detached", timeout=10000)
    for text in said:
        print("answered a front-end dialog:", text.replace("\n", " | "))
    return said


def run_cell(page, index: int) -> None:
    """Run cell ``index`` (Ctrl+Enter in it); a kernel that was not quite connected yet may drop
    the request, so run it again until the prompt says it runs or ran ([*] or [n])."""
    cell = page.locator(".jp-Notebook .jp-Cell").nth(index)
    prompt = cell.locator(".jp-InputPrompt").first
    for _ in range(8):
        dismiss_dialogs(page)
        try:
            cell.locator(".cm-content").click(timeout=15000)
        except Exception:  # noqa: BLE001 - a dialog came up in between: answer it, then again
            continue
        page.keyboard.press("Control+Enter")
        end = time.monotonic() + 15
        while time.monotonic() < end and prompt.inner_text().strip() in ("[ ]:", ""):
            time.sleep(0.25)
        if prompt.inner_text().strip() not in ("[ ]:", ""):
            return
    pytest.fail(f"cell {index} did not run; prompt {prompt.inner_text()!r}")


def wait_widget(page, d: Path):
    """The widget's canvas once it has drawn a frame."""
    canvas = page.locator("canvas.pf-canvas")
    try:
        canvas.wait_for(timeout=120000)
    except Exception:
        page.screenshot(path=str(d / "nb.png"))
        out = page.locator(".jp-OutputArea").all_inner_texts()
        pytest.fail(f"the widget did not appear; cell output: {out!r}; screenshot {d / 'nb.png'}")
    page.wait_for_function("() => Number(document.querySelector('canvas.pf-canvas').dataset.frames || 0) >= 1",
                           timeout=120000)
    return canvas


def pixels(locator):
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(locator.screenshot())).convert("RGB"))


def lit(img) -> int:
    """Pixels that differ from the background (the top-left pixel)."""
    return int((np.abs(img.astype(int) - img[0, 0].astype(int)).max(axis=2) > 40).sum())


def changed(a, b) -> float:
    return float((np.abs(a.astype(int) - b.astype(int)).max(axis=2) > 40).mean())
