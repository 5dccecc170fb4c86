"""Level-of-detail index build of a big LAZ: points/s against laspy's own chunked read.

The target (issue 30): the index build of a 100 M-point LAZ runs at >= 0.5 of the points/s
of laspy reading the same file in chunks (``chunk_iterator``, the same lazrs backend and
chunk size the build uses). Both are timed in the same run, interleaved (read, build, build,
read, ...), medians over ``--repeats``; each build starts from an empty cache directory.

The input: the real airborne LiDAR tile ``autzen_trim.laz`` (110,000 points, from
``../shared/data`` beside the checkout, env ``POINTFLOW_DATA``) is only 0.1 M points, so the
bench writes a LAZ of ``--points`` points made of copies of it shifted onto a grid of tiles
(same point format 3, scale, channels), with laspy/lazrs; it is kept in ``--workdir`` and
reused while its size matches.

    PYTHONPATH=. .venv/bin/python bench/bench_map_index.py                  # 100 M points, 2 repeats
    PYTHONPATH=. .venv/bin/python bench/bench_map_index.py --points 10000000 --repeats 3

Writes ``bench/results/map_index.json`` (or ``--out``) and a chart beside it; ``uptime``
before and after (the machine is shared: the load is part of every figure).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import time

import numpy as np

import _harness as harness


def data_dir() -> str:
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    return os.environ.get("POINTFLOW_DATA") or os.path.join(os.path.dirname(here), "shared", "data")


def tiled_laz(out: str, points: int) -> str:
    """``points`` points of autzen_trim.laz tiles on a grid (the last tile cut short)."""
    import laspy

    if os.path.exists(out):
        with laspy.open(out) as f:
            if f.header.point_count == points and f.header.are_points_compressed:
                return out
    src = laspy.read(os.path.join(data_dir(), "autzen_trim.laz"))
    h = laspy.LasHeader(point_format=src.header.point_format, version=src.header.version)
    h.scales, h.offsets = src.header.scales, src.header.offsets
    base = src.points.array
    tiles = -(-points // base.shape[0])
    side = int(np.ceil(np.sqrt(tiles)))
    step = (np.asarray(src.header.maxs[:2]) - np.asarray(src.header.mins[:2]) + 1.0) / np.asarray(h.scales[:2])
    tmp = out + ".part"
    with laspy.open(tmp, mode="w", header=h, do_compress=True, laz_backend=laspy.LazBackend.Lazrs) as w:
        left = points
        for i in range(tiles):
            a = base[:min(left, base.shape[0])].copy()
            a["X"] += int(round((i % side) * step[0]))
            a["Y"] += int(round((i // side) * step[1]))
            w.write_points(laspy.PackedPointRecord(a, h.point_format))
            left -= a.shape[0]
    os.replace(tmp, out)
    return out


def laspy_read(path: str) -> tuple[float, int]:
    """laspy's chunked read, as the build reads: same backend (lazrs, one thread), same chunks."""
    import laspy

    from pointflow.formats.las import laz_backend as _laz_backend
    from pointflow.map.inputs import CHUNK_POINTS

    t = time.perf_counter()
    n = 0
    with laspy.open(path, laz_backend=_laz_backend()) as f:
        for pts in f.chunk_iterator(CHUNK_POINTS):
            n += len(pts.array)
    return time.perf_counter() - t, n


def index_build(path: str, cache: str) -> tuple[float, dict]:
    from pointflow.map.build import build_index, index_dir

    shutil.rmtree(cache, ignore_errors=True)
    out = index_dir(path, cache)
    t = time.perf_counter()
    build_index(path, out, progress=False)
    dt = time.perf_counter() - t
    with open(os.path.join(out, "meta.json")) as f:
        meta = json.load(f)
    shutil.rmtree(cache, ignore_errors=True)
    return dt, {"nodes": meta["nodes"], "count": meta["count"]}


def chart(res: dict, png: str) -> None:
    plt = harness.pyplot()
    if plt is None:
        return
    fig, ax = plt.subplots(figsize=(7, 3.6))
    reads = [r["points_per_s"] / 1e6 for r in res["runs"] if r["what"] == "laspy_read"]
    builds = [r["points_per_s"] / 1e6 for r in res["runs"] if r["what"] == "index_build"]
    ax.bar(np.arange(len(reads)) - 0.2, reads, 0.4, label="laspy chunked read")
    ax.bar(np.arange(len(builds)) + 0.2, builds, 0.4, label="index build")
    ax.set_xticks(np.arange(len(reads)))
    ax.set_xlabel("repeat (interleaved: read, build, then build, read, ...)")
    ax.set_ylabel("M points/s")
    ax.set_title(f"LOD index build vs laspy read, {res['points'] / 1e6:.0f} M-point LAZ: "
                 f"ratio {res['ratio_median']:.2f} (target >= 0.5)", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--points", type=int, default=100_000_000)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--workdir", default="/tmp/pointflow-bench-map")
    ap.add_argument("--input", help="a LAZ to use instead of the tiled autzen file")
    ap.add_argument("--chart-only", action="store_true", help="redraw the chart from --out's JSON")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results",
                                                   "map_index.json"))
    a = ap.parse_args()
    if a.chart_only:
        with open(a.out) as f:
            chart(json.load(f), os.path.splitext(a.out)[0] + ".png")
        return
    os.makedirs(a.workdir, exist_ok=True)
    t = time.perf_counter()
    path = a.input or tiled_laz(os.path.join(a.workdir, f"autzen_tiled_{a.points}.laz"), a.points)
    made_s = time.perf_counter() - t
    cache = os.path.join(a.workdir, "cache")
    res = {"bench": "map_index", "command": harness.command(), "machine": harness.machine(),
           "input": path, "input_bytes": os.path.getsize(path),
           "input_note": None if a.input else "copies of the real autzen_trim.laz (110,000 points) on a grid of tiles",
           "runs": []}
    print(f"input {path} ({res['input_bytes'] / 1e6:.0f} MB, made/checked in {made_s:.0f} s); "
          f"{res['machine']['uptime_before']}", flush=True)
    for r in range(a.repeats):
        order = ("laspy_read", "index_build") if r % 2 == 0 else ("index_build", "laspy_read")
        for what in order:
            if what == "laspy_read":
                dt, n = laspy_read(path)
                extra = {}
            else:
                dt, extra = index_build(path, cache)
                n = extra["count"]
            run = {"repeat": r, "what": what, "seconds": round(dt, 3), "points": n,
                   "points_per_s": n / dt, "load1": os.getloadavg()[0], **extra}
            res["runs"].append(run)
            print(f"  {what:12s} {n / 1e6:.1f} M points in {dt:.1f} s: {n / dt / 1e6:.2f} M points/s "
                  f"(load {run['load1']:.1f})", flush=True)
    res["points"] = res["runs"][0]["points"]
    med = {w: statistics.median(r["points_per_s"] for r in res["runs"] if r["what"] == w)
           for w in ("laspy_read", "index_build")}
    res["laspy_read_points_per_s_median"] = med["laspy_read"]
    res["index_build_points_per_s_median"] = med["index_build"]
    res["ratio_median"] = med["index_build"] / med["laspy_read"]
    res["target"] = 0.5
    harness.machine_done(res["machine"])
    harness.write_result(a.out, res, indent=1)
    chart(res, os.path.splitext(a.out)[0] + ".png")
    print(f"ratio build/read (medians) {res['ratio_median']:.2f} (target >= 0.5); {res['machine']['uptime_after']}")


if __name__ == "__main__":
    main()
