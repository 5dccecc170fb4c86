"""A/B of the compiled cpu raster between two git revisions in one run: frame time per
configuration (2 px squares by intensity, 3 px round points, EDL, colour by height with the
automatic range, world-size points), split (points, bins) and thread count (1, 2), each
side's own ``pointflow`` in a fresh process per round, the sides alternating (ABBA):

    PYTHONPATH=$PWD .venv/bin/python bench/ab_cpu_raster.py --base 402b806 --sizes 1000000 100000
    PYTHONPATH=$PWD .venv/bin/python bench/ab_cpu_raster.py --base main --head . --only edl,by_z --splits bins

The measuring code is this file's (``--child``), run against either side's package, so both
sides are timed the same way: the scene of ``bench_cpu_threads.py`` (the autzen tile repeated
to N points, 1280x720, turbo, 1% of the ring rewritten per frame, output = read_image), 12
frames per (configuration, split, threads), the median of the last 10. Writes per size the
medians over rounds of each side and head/base into ``bench/results/ab_cpu_raster.json``.
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

CONFIGS = ("squares2", "round3", "edl", "by_z", "world")


def child(n: int, only: list[str], splits: list[str]) -> dict[str, float]:
    """One side, one round: median frame ms per configuration/split/threads."""
    import numba

    from _harness.scenes import H as HH, W, rewritten_frames, tiled_scene
    from pointflow.config import EdlConfig, RenderConfig
    from pointflow.render.cpu_compute import CpuComputeRenderer
    conf = {"squares2": {}, "round3": dict(point_size=3.0, point_shape="round"), "edl": dict(edl=EdlConfig(enabled=True)),
            "by_z": dict(color_by="z"), "world": dict(point_size_space="world", point_size=0.5)}
    os.environ["POINTFLOW_CPU_RASTER_ADAPTIVE"] = "0"
    f, cam = tiled_scene(n)
    out = {}
    for name in only:
        cfg = RenderConfig(**{**dict(size=[W, HH], color_by="intensity", colormap="turbo", point_size=2.0,
                                     gpu_timestamps=False, backend="cpu", raster="compute"), **conf[name]})
        for sp in splits:
            os.environ["POINTFLOW_CPU_RASTER_SPLIT"] = sp
            r = CpuComputeRenderer(cfg, n, ["intensity"])
            head = 0
            for t in (1, 2):
                numba.set_num_threads(min(t, numba.config.NUMBA_NUM_THREADS))
                f.dirty = None
                r.render(f, cam)
                ts, _, head = rewritten_frames(r, f, cam, 12, head)
                out[f"{name}/{sp}/{t}T"] = float(np.median(ts[2:]))
            r.close()
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    H.ab_arguments(ap, [1_000_000, 100_000], 8, "ab_cpu_raster.json")
    ap.add_argument("--only", default=",".join(CONFIGS))
    ap.add_argument("--splits", default="points,bins")
    a = ap.parse_args(argv)
    only, splits = a.only.split(","), a.splits.split(",")
    if a.child:
        print(json.dumps(child(a.child, only, splits)))
        return 0
    if not a.base:
        ap.error("--base is required")
    machine = H.machine()
    me = str(Path(__file__).resolve())
    bsha, hsha, rows = H.ab_child_rounds(
        me, a.base, a.head, a.sizes, a.rounds, lambda n: ["--child", str(n), "--only", a.only, "--splits", a.splits],
        warm=["--child", "1000", "--only", only[0], "--splits", splits[0]])  # compile (or load) each side's loops
    H.write_result(a.out, {"base": bsha, "head": hsha, "rows": rows, "machine": H.machine_done(machine),
                           "measured_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "command": H.command()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
