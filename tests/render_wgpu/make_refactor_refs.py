"""Record the wgpu tier's images on the tier-agreement scenes (tests/render_tiers) for each
raster method, as ``data/refactor_refs.npz``: ``test_refactor_refs.py`` checks that the
strategies refactor (issue 17) left every image byte-identical.

Made once from main's code before the refactor (commit b2b1037) on Mesa lavapipe:

    XDG_RUNTIME_DIR=/tmp/xdg .venv/bin/python tests/render_wgpu/make_refactor_refs.py

Re-record only for an intended change of the images (and say so in the commit).
"""
from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
OUT = HERE / "data" / "refactor_refs.npz"
METHODS = {"quads": ("quads", None), "compute": ("compute", None), "compute32": ("compute", False)}


def scenes():
    sys.path.insert(0, str(HERE.parent))
    sys.path.insert(0, str(HERE.parent / "render_tiers"))  # its conftest first
    from test_agreement import SCENES  # noqa: E402
    return SCENES


def render_all(adapter) -> dict[str, np.ndarray]:
    SCENES = scenes()
    from scenes import render_cfg  # noqa: E402 (tests/render_tiers is on sys.path now)

    from pointflow.render.wgpu_tier import WgpuRenderer
    out = {}
    for name, build in SCENES.items():
        frame, cam, kw = build()
        cfg = render_cfg(size=[320, 240], **kw)
        for m, (raster, key64) in METHODS.items():
            r = WgpuRenderer(dataclasses.replace(cfg, raster=raster), frame.capacity, list(frame.channels),
                             adapter=adapter, key64=key64)
            try:
                r.render(frame, cam)
                out[f"{name}/{m}"] = r.read_image()
            finally:
                r.close()
    return out


def main() -> int:
    os.environ.setdefault("XDG_RUNTIME_DIR", "/tmp/xdg")
    os.makedirs(os.environ["XDG_RUNTIME_DIR"], exist_ok=True)
    sys.path.insert(0, str(HERE.parents[1]))
    from pointflow.render.wgpu_tier import select_adapter
    adapter, why = select_adapter()
    if adapter is None:
        raise SystemExit(why)
    imgs = render_all(adapter)
    OUT.parent.mkdir(exist_ok=True)
    np.savez_compressed(OUT, **imgs)
    print(f"wrote {len(imgs)} images to {OUT} ({OUT.stat().st_size} bytes)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
