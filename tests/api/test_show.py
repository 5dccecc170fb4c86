"""pointflow.show without a display: one PNG, its path printed, the cloud drawn in it
(issue 28, item 5). The notebook hook: a registered view is taken first."""
from __future__ import annotations

import numpy as np
from PIL import Image

import pointflow.quickshow as qs

from .helpers import run_script


def test_show_writes_a_png_and_prints_its_path(tmp_path):
    p = run_script(tmp_path, """
import os
os.environ.pop("DISPLAY", None); os.environ.pop("WAYLAND_DISPLAY", None)
import numpy as np
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
