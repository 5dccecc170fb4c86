"""docs/img/notebook_widget.png: the notebook widget in a real JupyterLab and headless Chromium
(the replay of tests/notebook/test_widget_controls.py at scan 4, a measure between two points).

    PYTHONPATH=. python scripts/notebook_screenshot.py docs/img/notebook_widget.png
"""
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tests.notebook.helpers import browser_page, jupyter, need, open_notebook, run_cell, wait_widget, write_notebook  # noqa: E402
from tests.notebook.test_widget_controls import REPLAY  # noqa: E402


def main(out: str) -> None:
    sync_api = need("lab")
    cell = (REPLAY.replace("p.playback(step=1)", "p.playback(seek_s=2.0)")
            .replace("width=320, height=240", "width=560, height=320").replace('"size": [320, 240]', '"size": [560, 320]'))
    with jupyter(Path(tempfile.mkdtemp()), "lab") as (url, token, d, page_path), browser_page(sync_api) as page:
        write_notebook(d / "shot.ipynb", cell)
        open_notebook(page, url, token, page_path, "shot.ipynb")
        run_cell(page, 0)
        canvas = wait_widget(page, d)
        page.wait_for_function("() => document.querySelector('canvas.pf-canvas').dataset.mime === 'image/png'",
                               timeout=60000)
        page.select_option(".pointflow-view select.pf-mode", "measure")
        box = canvas.bounding_box()
        cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
        page.mouse.click(cx - 120, cy + 20)
        page.wait_for_function("() => document.querySelector('.pointflow-view .pf-info').textContent.includes('first')",
                               timeout=60000)
        page.mouse.click(cx + 110, cy - 30)
        page.wait_for_function("() => document.querySelector('canvas.pf-canvas').dataset.distance !== undefined",
                               timeout=60000)
        page.wait_for_function("() => document.querySelector('.pointflow-view .pf-timeline').dataset.index === '4'",
                               timeout=60000)
        time.sleep(1.5)  # the stats line fills in
        page.add_style_tag(content=".Toastify { display: none !important; }")  # JupyterLab's news toast
        page.locator(".pointflow-view").screenshot(path=out)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "docs/img/notebook_widget.png")
