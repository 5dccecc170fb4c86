"""Footprint LOD (``render.lod_fill``, issue 41): frame time against image error, per tier.

The scene of ``bench_wgpu_compact.py`` (the autzen tile repeated to N points, 1280x720, 2 px
squares, turbo by intensity, 1% of the ring rewritten per frame), three views: the whole ring
(top down), the whole ring from 3x farther, and an oblique view across it (near tiles
big, far tiles small). Per view, tier and fill (off, then ``lod_fill`` 8, 4, 2, 1, 0.5):
the median frame time (render + read_image), the median of the per-round ratios to the
same tier without LOD (frames interleaved in rotating order, so load drifts hit every
side), the points drawn, and the error against that tier's own image without LOD: PSNR
(RGB), the share of pixels that differ, the IoU of lit pixels.

    PYTHONPATH=$PWD .venv/bin/python bench/bench_lod_fill.py --points 1000000
    PYTHONPATH=$PWD .venv/bin/python bench/bench_lod_fill.py --points 4000000 --shape round --point-size 3 \
        --out bench/results/lod_fill_round_4m.json     # the compiled raster's general loops

Writes ``bench/results/lod_fill.json`` and ``lod_fill.png`` (time ratio against share of
pixels differing, a line per tier and view, each point labelled by its fill).
"""
from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Optional

import numpy as np

import _harness
from _harness.scenes import H, W, camera_for, tiled_frame
from _harness.tiers import errors, make_tier
from pointflow.config import RenderConfig

FILLS = (0.0, 8.0, 4.0, 2.0, 1.0, 0.5)
TIERS = ("cpu-compute", "wgpu-compute")


def cameras(world: np.ndarray) -> dict[str, Any]:
    from pointflow.render.camera import Camera
    lo, hi = world.min(0), world.max(0)
    whole = camera_for(world)
    tgt = np.asarray(whole.target, np.float64)
    eye = tgt + 3.0 * (np.asarray(whole.eye, np.float64) - tgt)
    far = Camera(eye=eye, target=tgt, up=whole.up, fov_deg=whole.fov_deg, near=whole.near, far=whole.far * 10)
    ext = hi - lo
    low = Camera(eye=[tgt[0], lo[1] - 0.25 * ext[1], hi[2] + 0.3 * ext[1]], target=[tgt[0], tgt[1], lo[2]],
                 up=[0, 0, 1], fov_deg=60.0, near=0.002 * ext[1], far=4 * ext[1])
    return {"whole": whole, "far": far, "oblique": low}


def run(n: int, rounds: int, tiers: tuple[str, ...], shape: str = "square", point_px: float = 2.0) -> dict[str, Any]:
    machine = _harness.machine()
    f, world, scene = tiled_frame(n)
    cams = cameras(world)
    del world
    cfg = RenderConfig(size=[W, H], color_by="intensity", colormap="turbo", point_size=point_px, point_shape=shape,
                       gpu_timestamps=False)
    out: dict[str, Any] = {}
    step = max(n // 100, 1)
    for tier in tiers:
        rs = {fill: make_tier(tier, replace(cfg, lod_fill=fill), n) for fill in FILLS}
        if any(r is None for r in rs.values()):  # (make_tier said why)
            for r in rs.values():
                if r is not None:
                    r.close()
            continue
        try:
            for v, cam in cams.items():
                wall: dict[float, list[float]] = {k: [] for k in FILLS}
                drawn: dict[float, Any] = {}
                imgs: dict[float, np.ndarray] = {}
                for fill, r in rs.items():  # first frame: the whole ring uploaded
                    f.dirty = None
                    r.render(f, cam)
                    r.read_image()
                head = 0
                for i in range(rounds):
                    order = list(FILLS[i % len(FILLS):] + FILLS[:i % len(FILLS)])
                    for fill in order:
                        a, b = head, min(head + step, n)
                        head = b % n
                        f.dirty = [(a, b)]
                        t0 = time.perf_counter()
                        st = rs[fill].render(f, cam)
                        imgs[fill] = rs[fill].read_image()
                        wall[fill].append((time.perf_counter() - t0) * 1e3)
                        st = (rs[fill].finish() or st) if hasattr(rs[fill], "finish") else st
                        drawn[fill] = st.drawn
                off = np.asarray(wall[0.0])
                bg = imgs[0.0][0, 0].copy()
                rows = {}
                for fill in FILLS:
                    e = errors(imgs[fill], imgs[0.0], bg)
                    rows[str(fill)] = {"median_ms": float(np.median(wall[fill])),
                                       "over_off": float(np.median(np.asarray(wall[fill]) / off)),
                                       "drawn": drawn[fill], **e}
                    print(f"  {tier:12} {v:8} fill {fill:4g}: {rows[str(fill)]['median_ms']:7.1f} ms "
                          f"x{rows[str(fill)]['over_off']:.2f}, drawn {drawn[fill]}, PSNR {e['psnr_db']:.1f} dB, "
                          f"differ {e['diff_fraction']:.2%}, IoU {e['coverage_iou']:.3f}", flush=True)
                out.setdefault(tier, {})[v] = rows
        finally:
            for r in rs.values():
                r.close()
    return {"points": n, "rounds": rounds, "scene": scene, "size": [W, H], "point_shape": shape, "point_size": point_px,
            "fills": list(FILLS), "tiers": out,
            "cpu_split": os.environ.get("POINTFLOW_CPU_RASTER_SPLIT"),
            "machine": _harness.machine_done(machine), "command": _harness.command(),
            "measured_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


def chart(res: dict[str, Any], path: Path) -> None:
    if (plt := _harness.pyplot()) is None:
        return
    fig, ax = plt.subplots(figsize=(8.5, 5.2))
    styles = {"whole": "-", "far": "--", "oblique": ":"}
    colours = {"cpu-compute": "tab:purple", "wgpu-compute": "tab:red", "cpu": "tab:blue", "wgpu-quads": "tab:green"}
    for tier, views in res["tiers"].items():
        for v, rows in views.items():
            fills = [k for k in rows if float(k) > 0]
            x = [rows[k]["over_off"] for k in fills]
            y = [max(rows[k]["diff_fraction"], 1e-4) for k in fills]
            ax.plot(x, y, styles.get(v, "-"), marker="o", color=colours.get(tier, "grey"), label=f"{tier}, {v}")
            for k, xi, yi in zip(fills, x, y):
                ax.annotate(f"{float(k):g}", (xi, yi), textcoords="offset points", xytext=(4, 3), fontsize=7)
    ax.set_yscale("log")
    ax.set_xlabel("frame time / the same tier without LOD (median of per-round ratios)")
    ax.set_ylabel("share of pixels that differ from no LOD")
    ax.set_title(f"footprint LOD (render.lod_fill, labels) at {res['points']:,} points, {res['size'][0]}x{res['size'][1]}, "
                 f"{res.get('point_size', 2.0):g} px {res.get('point_shape', 'square')}",
                 fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--rounds", type=int, default=7, help="frames per (view, fill), interleaved")
    ap.add_argument("--tiers", default=",".join(TIERS), help="cpu-compute, cpu, wgpu-compute, wgpu-quads")
    ap.add_argument("--split", default="points",
                    help="the cpu raster's split (POINTFLOW_CPU_RASTER_SPLIT; default points, the rule at <= 2 "
                         "threads: the adaptive choice would time both per renderer and may differ between fills)")
    ap.add_argument("--shape", default="square", choices=("square", "round"),
                    help="render.point_shape (round: the compiled raster's general loops)")
    ap.add_argument("--point-size", type=float, default=2.0, help="render.point_size in pixels")
    ap.add_argument("--out", default=None, help="default bench/results/lod_fill.json")
    a = ap.parse_args(argv)
    os.environ["POINTFLOW_CPU_RASTER_SPLIT"] = a.split
    res = run(a.points, a.rounds, tuple(a.tiers.split(",")), a.shape, a.point_size)
    p = _harness.write_result(a.out or _harness.RESULTS / "lod_fill.json", res)
    chart(res, p.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
