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
from typing import Any

import numpy as np

import _harness as H

CONFIGS = ("squares2", "round3", "edl", "by_z", "world")


def child(n: int, only: list[str], splits: list[str]) -> dict[str, float]:
    """One side, one round: median frame ms per configuration/split/threads."""
    import numba

    from _harness.scenes import H as HH, W, base_cloud, camera_for, make_frame, tiled
    from pointflow.config import EdlConfig, RenderConfig
    from pointflow.render.cpu_compute import CpuComputeRenderer
    conf = {"squares2": {}, "round3": dict(point_size=3.0, point_shape="round"), "edl": dict(edl=EdlConfig(enabled=True)),
            "by_z": dict(color_by="z"), "world": dict(point_size_space="world", point_size=0.5)}
    os.environ["POINTFLOW_CPU_RASTER_ADAPTIVE"] = "0"
    base, inten0, _ = base_cloud()
    world, inten = tiled(base, inten0, n)
    f = make_frame(world, inten)
    cam = camera_for(world)
    out = {}
    for name in only:
        cfg = RenderConfig(**{**dict(size=[W, HH], color_by="intensity", colormap="turbo", point_size=2.0,
                                     gpu_timestamps=False, backend="cpu", raster="compute"), **conf[name]})
        for sp in splits:
            os.environ["POINTFLOW_CPU_RASTER_SPLIT"] = sp
            r = CpuComputeRenderer(cfg, n, ["intensity"])
            step, head = max(n // 100, 1), 0
            for t in (1, 2):
                numba.set_num_threads(min(t, numba.config.NUMBA_NUM_THREADS))
                f.dirty = None
                r.render(f, cam)
                ts = []
                for _ in range(12):
                    a = head
                    f.dirty = [(a, min(a + step, n))]
                    head = (head + step) % n
                    t0 = time.perf_counter()
                    r.render(f, cam)
                    r.read_image()
                    ts.append((time.perf_counter() - t0) * 1e3)
                out[f"{name}/{sp}/{t}T"] = float(np.median(ts[2:]))
            r.close()
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", help="the revision to compare against (required)")
    ap.add_argument("--head", default=".", help="a revision, or . for this checkout as it is (default)")
    ap.add_argument("--sizes", type=int, nargs="*", default=[1_000_000, 100_000])
    ap.add_argument("--rounds", type=int, default=8, help="rounds per size (each: one process per side)")
    ap.add_argument("--only", default=",".join(CONFIGS))
    ap.add_argument("--splits", default="points,bins")
    ap.add_argument("--out", default=str(H.RESULTS / "ab_cpu_raster.json"))
    ap.add_argument("--child", type=int, default=0, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    only, splits = a.only.split(","), a.splits.split(",")
    if a.child:
        print(json.dumps(child(a.child, only, splits)))
        return 0
    if not a.base:
        ap.error("--base is required")
    machine = H.machine()
    me = str(Path(__file__).resolve())
    rows = []
    with H.checkout_or_revision(a.base) as (bdir, bsha), H.checkout_or_revision(a.head) as (hdir, hsha):
        sides = {"base": bdir, "head": hdir}
        for side, d in sides.items():  # compile (or load) each side's loops before timing
            H.run_json([me, "--child", "1000", "--only", only[0], "--splits", splits[0]], d)
        for n in a.sizes:
            got: dict[str, list[dict[str, float]]] = {"base": [], "head": []}
            for i in range(a.rounds):
                for side in (("base", "head") if i % 2 == 0 else ("head", "base")):
                    got[side].append(H.run_json([me, "--child", str(n), "--only", a.only, "--splits", a.splits],
                                                sides[side]))
            row: dict[str, Any] = {"points": n, "rounds": a.rounds, "load_after": [round(x, 2) for x in os.getloadavg()],
                                   "figures": {}}
            for k in got["base"][0]:
                b = float(np.median([r[k] for r in got["base"]]))
                h = float(np.median([r[k] for r in got["head"]]))
                row["figures"][k] = {"base_ms": round(b, 2), "head_ms": round(h, 2), "head_over_base": round(h / b, 3),
                                     "base_samples": [round(r[k], 2) for r in got["base"]],
                                     "head_samples": [round(r[k], 2) for r in got["head"]]}
                print(f"{n:>9,} {k:22s} base {b:7.2f} ms  head {h:7.2f} ms  x{h / b:.2f}", flush=True)
            rows.append(row)
    H.write_result(a.out, {"base": bsha, "head": hsha, "rows": rows, "machine": H.machine_done(machine),
                           "measured_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "command": H.command()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
