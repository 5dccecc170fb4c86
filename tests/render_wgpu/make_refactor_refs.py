"""Record the wgpu tier's images on the tier-agreement scenes (tests/render_tiers) for each
raster method, as ``data/refactor_refs.npz``: ``test_refactor_refs.py`` checks that the
strategies refactor (issue 17) left every image byte-identical.

Made once from main's code before the refactor (commit b2b1037) on Mesa lavapipe:

    XDG_RUNTIME_DIR=/tmp/xdg .venv/bin/python tests/render_wgpu/make_refactor_refs.py

Re-record only for an intended change of the images (and say so in the commit). Re-recorded
for issue 31 item 6: the quads images changed on purpose (footprints decided per pixel
centre, linear depth; 0.05-0.16% of their pixels); the compute images are unchanged.
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


def _scenes_module():
    """tests/render_tiers/scenes.py, loaded by path (its directory's conftest must not shadow ours)."""
    import importlib.util
    spec = importlib.util.spec_from_file_location("render_tiers_scenes", HERE.parent / "render_tiers" / "scenes.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)  # type: ignore[union-attr]
    return mod


def scenes():
    """The scenes of tests/render_tiers/test_agreement.py (same builders, same parameters)."""
    from pointflow.render.camera import Camera
    S = _scenes_module()
    geo = np.array([6.4e5, 4.9e6, 120.0])

    def terrain():
        w = S.terrain(20_000)
        f = S.make_frame(w, capacity=24_000, head=20_000, intensity=((w[:, 2] + 3) / 14).astype(np.float32))
        return f, S.terrain_camera(), dict(point_size=2)

    def sphere():
        w = S.sphere_shell(15_000)
        f = S.make_frame(w, intensity=np.linspace(0, 1, len(w), dtype=np.float32))
        cam = Camera(eye=[30, -25, 12], target=[0, 0, 0], near=5, far=80)
        return f, cam, dict(point_size=5, point_shape="round", colormap="viridis")

    def geo_height():
        w = S.terrain(15_000) + geo
        f = S.make_frame(w, origin=geo)
        cam = S.terrain_camera().translated(geo)
        return f, cam, dict(point_size=3, color_by="z", color_range="auto", colormap="grayscale")

    def world_rgb_filters():
        w = S.terrain(20_000, seed=7)
        rgb = (np.abs(w) * 9 % 255).astype(np.uint8)
        t = np.linspace(0, 1000, len(w))
        imp = np.abs(np.sin(w[:, 0])).astype(np.float32)
        f = S.make_frame(w, capacity=22_000, head=15_000, rgb=rgb, t_ms=t, importance=imp, now_ms=1000.0, seed=11)
        return f, S.terrain_camera(), dict(point_size=0.4, point_size_space="world", color_by="rgb",
                                           time_window_ms=700.0, importance_sampling=True)

    return {"terrain": terrain, "sphere": sphere, "georeferenced": geo_height,
            "world_rgb_filters": world_rgb_filters}, S.render_cfg


def render_all(adapter) -> dict[str, np.ndarray]:
    SCENES, render_cfg = scenes()

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
