"""pointflow.show without a display: one PNG, its path printed, the cloud drawn in it
(issue 28, item 5). The notebook hook: a registered view is taken first."""
from __future__ import annotations

import sys

import numpy as np
import pytest
from PIL import Image

import pointflow.show  # noqa: F401 - the module (pointflow.show is its function)

qs = sys.modules["pointflow.show"]

from .helpers import run_script


def test_show_writes_a_png_and_prints_its_path(tmp_path):
    p = run_script(tmp_path, """
import os
os.environ.pop("DISPLAY", None); os.environ.pop("WAYLAND_DISPLAY", None)
import sys

import numpy as np
import pytest
import pointflow
xyz = np.random.default_rng(3).normal(size=(5000, 3)).astype(np.float32)
ret = pointflow.show(xyz, intensity=np.abs(xyz[:, 2]), path="cloud.png", size=(160, 120))
print("RETURNED", ret)
seq = pointflow.show([xyz[:2500], xyz[2500:] + 10], size=(160, 120))   # a sequence, a temporary file
print("RETURNED", seq)
""")
    lines = p.stdout.split("\n")
    png = str(tmp_path / "cloud.png")
    assert lines[0] == png and f"RETURNED {png}" in lines
    seq = next(l for l in lines if l.startswith("RETURNED /") and l != f"RETURNED {png}")[len("RETURNED "):]
    try:
        for path in (png, seq):
            img = np.asarray(Image.open(path).convert("RGB"), dtype=int)
            assert img.shape == (120, 160, 3)
            bg = img[0, 0]
            lit = np.abs(img - bg).sum(axis=2) > 30
            assert lit.sum() > 500, path  # the cloud is drawn, not only the background
    finally:
        if seq.startswith("/tmp/") or "pointflow-show-" in seq:
            import os

            os.unlink(seq)


def test_a_registered_view_is_tried_first():
    calls = []
    view = qs.View("notebook", lambda: True, lambda p, total, path, timeout: calls.append(total) or "shown")
    saved = list(qs.VIEWS)
    try:
        qs.register_view(view)
        assert [v.name for v in qs.VIEWS] == ["notebook", "window", "png"]
        assert qs.show(np.zeros((7, 3), np.float32)) == "shown" and calls == [7]
    finally:
        qs.VIEWS[:] = saved
    assert not qs.in_notebook()


@pytest.mark.timeout(900)
def test_show_opens_a_window_where_there_is_a_display(tmp_path):
    """Under Xvfb: a window opens (the render stage says so); Ctrl-C returns None and the
    pipeline stops cleanly. The guarantee is that it happens, not how fast: on a loaded
    2-core machine starting four interpreters and a window takes tens of seconds, so the
    test waits on the script's own lines (read by a thread: a silent script cannot block
    the wait) up to bounds far above what a loaded machine takes, never a fixed sleep."""
    import os
    import queue
    import signal
    import subprocess
    import sys
    import threading
    import time

    from gpu_util import xvfb_display

    from .helpers import REPO

    pytest.importorskip("rendercanvas", reason="the window extra: pip install 'pointflow[window]'")
    pytest.importorskip("glfw", reason="the window extra: pip install 'pointflow[window]'")
    script = tmp_path / "win.py"
    script.write_text("""
import numpy as np, pointflow
print("RETURNED", pointflow.show(np.random.default_rng(0).normal(size=(3000, 3)), size=(160, 120)), flush=True)
""")
    with xvfb_display() as display:
        env = dict(os.environ, DISPLAY=display, PYTHONPATH=str(REPO))
        proc = subprocess.Popen([sys.executable, str(script)], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        lines: queue.Queue = queue.Queue()
        reader = threading.Thread(target=lambda: [lines.put(ln) for ln in proc.stderr] + [lines.put(None)], daemon=True)
        reader.start()
        err = []
        try:
            end = time.monotonic() + 600  # the window opens once every stage started: tens of s under load
            while time.monotonic() < end:
                try:
                    ln = lines.get(timeout=1.0)
                except queue.Empty:
                    continue
                if ln is None:
                    break
                err.append(ln)
                if "window open" in ln:
                    break
            assert any("pointflow.show: window open; close it to return" in ln for ln in err), "".join(err)[-3000:]
            proc.send_signal(signal.SIGINT)
            out = proc.stdout.read()  # until it exits: the stages stopped in waves, 5 s each at most
            proc.wait(timeout=240)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        reader.join(10)
        while True:
            try:
                ln = lines.get_nowait()
            except queue.Empty:
                break
            if ln is not None:
                err.append(ln)
    assert proc.returncode == 0, "".join(err)[-3000:]
    assert "RETURNED None" in out


def test_the_png_is_drawn_in_process_and_is_the_render_stages_picture(tmp_path):
    """Issue 36.5: a PNG show starts no stage (no supervisor is even imported), and its picture
    is the one the render stage's cpu reference draws of the same cloud through a pipeline."""
    from pointflow import Pipeline

    p = run_script(tmp_path, """
import sys
import sys

import numpy as np
import pointflow
xyz = np.random.default_rng(5).normal(size=(4000, 3)) * [3, 2, 1] + [1e5, -2e5, 30]   # georeferenced
print(pointflow.show(xyz, intensity=np.abs(xyz[:, 2] - 30), path="a.png", size=(160, 120), view="png"))
print("SUPERVISOR", "pointflow.runtime.supervisor" in sys.modules)
""")
    a = str(tmp_path / "a.png")
    assert p.stdout.split("\n")[:3] == [a, a, "SUPERVISOR False"], p.stdout  # printed, returned
    xyz = np.random.default_rng(5).normal(size=(4000, 3)) * [3, 2, 1] + [1e5, -2e5, 30]
    cfg = qs.show_config(len(xyz), ["intensity"], "intensity", (160, 120),
                         {"backend": "cpu", "raster": "reference"})
    cfg.supervisor.standby = False
    with Pipeline(cfg, out_dir="") as pipe:
        pipe.send(xyz, source="show", intensity=np.abs(xyz[:, 2] - 30))
        qs._show_png(pipe, len(xyz), str(tmp_path / "b.png"), 120)
    a, b = (np.asarray(Image.open(tmp_path / f).convert("RGB"), dtype=int) for f in ("a.png", "b.png"))
    assert (np.abs(a - a[0, 0]).sum(axis=2) > 30).sum() > 500  # the cloud is drawn
    assert np.array_equal(a, b)


def test_a_pipeline_with_no_source_takes_send():
    """Issue 36.5: ``Pipeline.from_dict`` with no source, and ``Pipeline()``, imply one ``api``
    source named ``api``: ``send`` works without declaring it."""
    from pointflow import Pipeline

    assert [(s.name, s.transport) for s in Pipeline().cfg.sources] == [("api", "api")]
    cfg = {"ring": {"max_points": 10_000}, "cadence": {"target_hz": 5}, "tracing": {"enabled": False},
           "render": {"backend": "cpu", "size": [32, 24], "output": {"dir": None}}, "supervisor": {"standby": False}}
    xyz = np.random.default_rng(0).normal(size=(1000, 3)).astype(np.float32)
    with Pipeline.from_dict(cfg) as p:
        assert p.send(xyz) == 1000
        p.wait(None, until=lambda: p.stats()["accounting"].get("ingest_written", 0) >= 1000)
        st = p.stats()
    assert st["stages"]["api"]["points_out"] == 1000 and st["accounting"]["ingest_written"] == 1000, st["accounting"]
