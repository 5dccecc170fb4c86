"""How far each wgpu raster method's image is from the float64 cpu tier on the autzen scan
(issue 31 item 6): 480x320, colour by z (automatic range), 2 px squares, EDL off and on.

    POINTFLOW_DATA=/work/shared/data .venv/bin/python bench/quads_agreement.py

Prints and writes ``bench/results/quads_agreement.json``: per method and EDL setting, the
fraction of pixels that differ from the cpu image at all and by more than one 8-bit step.
Run it from another checkout (``PYTHONPATH=<checkout>``) to compare code versions.
"""
from __future__ import annotations

import dataclasses
import json
import os
import platform
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))
os.environ.setdefault("XDG_RUNTIME_DIR", "/tmp/xdg")
os.makedirs(os.environ["XDG_RUNTIME_DIR"], exist_ok=True)

from bench_tiers import scene_autzen  # noqa: E402

from pointflow.config import EdlConfig, RenderConfig  # noqa: E402
from pointflow.render.cpu import CpuRenderer  # noqa: E402
from pointflow.render.wgpu_tier import WgpuRenderer  # noqa: E402

W, H = 480, 320


def _img(r, frame, cam) -> np.ndarray:
    r.render(frame, cam)
    out = r.read_image()
    if hasattr(r, "close"):
        r.close()
    return out


def main() -> int:
    scene = scene_autzen(W / H)
    if scene is None:
        print("autzen_trim.laz not found (set POINTFLOW_DATA)")
        return 1
    frame, cam, desc = scene
    rows = []
    for edl in (False, True):
        cfg = RenderConfig(size=[W, H], point_size=2, color_by="z", color_range="auto", edl=EdlConfig(enabled=edl))
        ref = _img(CpuRenderer(cfg, frame.capacity, list(frame.channels)), frame, cam)
        for m in ("quads", "compute"):
            img = _img(WgpuRenderer(dataclasses.replace(cfg, raster=m), frame.capacity, list(frame.channels)),
                       frame, cam)
            row = {"method": m, "edl": edl, "differ": float((img != ref).any(-1).mean()),
                   "beyond_one_step": float((np.abs(img.astype(np.int16) - ref).max(-1) > 1).mean())}
            rows.append(row)
            print(f"{m:8s} edl={'on ' if edl else 'off'}  differ {row['differ']:.4%}  "
                  f"> 1 step {row['beyond_one_step']:.4%}")
    out = ROOT / "results" / "quads_agreement.json"
    out.write_text(json.dumps({"scene": desc, "size": [W, H], "point_size": 2, "color_by": "z",
                               "host": platform.node(), "rows": rows}, indent=1) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
