"""A/B of the tiers' per-frame cost between two git revisions in one run: the numpy
reference (``cpu``), the gl tier and the wgpu compute method (whole frame, and its CPU side
``cpu_total``: planning, culling, compact positions, upload, encode, submit), each side's
own ``pointflow`` in a fresh process per round, the sides alternating (ABBA):

    PYTHONPATH=$PWD .venv/bin/python bench/ab_tier_frames.py --base 03fc4c6 --sizes 1000000

The measuring code is this file's (``--child``), run against either side's package. Scene:
``bench_cpu_threads.py``'s (the autzen tile repeated to N points, 1280x720, 2 px, 1% of the
ring rewritten per frame, output = read_image; for wgpu also ``streamed``: the wall time per
frame of 12 frames back to back without readback, as a live window draws), coloured by
intensity (the handoff's range)
and by height (the range reduced from the points); the wgpu tier with compact positions off
and on (``POINTFLOW_WGPU_COMPACT``: ``auto`` turns them on on a real GPU, off on lavapipe).
Per (tier, colour) 7 frames, the median of the last 5. Writes per size the medians over
rounds of each side and head/base into ``bench/results/ab_tier_frames.json``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

import _harness as H

TIERS = ("cpu", "gl", "wgpu", "wgpu_compact")
COLOURS = ("intensity", "z")


def child(n: int, tiers: list[str]) -> dict[str, float]:
    """One side, one round: median frame ms per tier/colour (and the wgpu CPU side)."""
    from dataclasses import replace

    from _harness.scenes import H as HH, W, rewritten_frames, streamed_frames, tiled_scene
    from pointflow.config import RenderConfig
    f, cam = tiled_scene(n)
    out = {}
    for tier in tiers:
        for colour in COLOURS:
            cfg = RenderConfig(size=[W, HH], color_by=colour, colormap="turbo", point_size=2.0, gpu_timestamps=False)
            if tier == "cpu":
                from pointflow.render.cpu import CpuRenderer
                r = CpuRenderer(replace(cfg, backend="cpu"), n, ["intensity"])
            elif tier == "gl":
                from pointflow.render.gl import GlRenderer
                r = GlRenderer(replace(cfg, backend="gl"), n, ["intensity"])
            else:
                os.environ["POINTFLOW_WGPU_COMPACT"] = "1" if tier == "wgpu_compact" else "0"
                from pointflow.render.wgpu_tier import WgpuRenderer
                r = WgpuRenderer(replace(cfg, backend="wgpu", raster="compute"), n, ["intensity"])
            f.dirty = None
            r.render(f, cam)
            r.read_image()
            ts, stats, _ = rewritten_frames(r, f, cam, 7)
            cpu_side = [st.timings_ms.get("cpu_total", np.nan) for st in stats]
            out[f"{tier}/{colour}"] = float(np.median(ts[2:]))
            if tier.startswith("wgpu"):
                out[f"{tier}/{colour}/cpu_side"] = float(np.median(cpu_side[2:]))
                out[f"{tier}/{colour}/streamed"], _ = streamed_frames(r, f, cam, 12)
            r.close()
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    H.ab_arguments(ap, [1_000_000], 4, "ab_tier_frames.json")
    ap.add_argument("--tiers", default=",".join(TIERS))
    a = ap.parse_args(argv)
    tiers = a.tiers.split(",")
    if a.child:
        print(json.dumps(child(a.child, tiers)))
        return 0
    if not a.base:
        ap.error("--base is required")
    machine = H.machine()
    me = str(Path(__file__).resolve())
    bsha, hsha, rows = H.ab_child_rounds(me, a.base, a.head, a.sizes, a.rounds,
                                         lambda n: ["--child", str(n), "--tiers", a.tiers], digits=3)
    H.write_result(a.out, {"base": bsha, "head": hsha, "rows": rows, "machine": H.machine_done(machine),
                           "measured_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "command": H.command()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
