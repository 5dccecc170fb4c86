"""How far each wgpu raster method's image is from the float64 cpu tier on the autzen scan
(issue 31 item 6): 480x320, colour by z (automatic range), 2 px squares, EDL off and on.

    POINTFLOW_DATA=/work/shared/data .venv/bin/python bench/quads_agreement.py

Prints and writes ``bench/results/quads_agreement.json``: per method and EDL setting, the
fraction of pixels that differ from the cpu image at all and by more than one 8-bit step.
Run it from another checkout (``PYTHONPATH=<checkout>``) to compare code versions.
"""
from __future__ import annotations

import dataclasses
import sys

import numpy as np

import _harness
from _harness.scenes import scene_autzen
from pointflow.config import EdlConfig, RenderConfig
from pointflow.render.cpu import CpuRenderer
from pointflow.render.wgpu_tier import WgpuRenderer

W, H = 480, 320


def _img(r, frame, cam) -> np.ndarray:
    r.render(frame, cam)
    out = r.read_image()
    if hasattr(r, "close"):
        r.close()
    return out


def main() -> int:
    machine = _harness.machine()
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
    _harness.write_result(_harness.RESULTS / "quads_agreement.json",
                          {"scene": desc, "size": [W, H], "point_size": 2, "color_by": "z",
                           "machine": _harness.machine_done(machine), "rows": rows}, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
