"""Does a map's first index build get its fair share of the CPU beside the live stages (issue 37)?

The map: ``autzen_trim.laz`` (real airborne points, ../shared/data) laid out as 7 tiles in
metres at UTM coordinates and cut to 697,721 points, one LAZ written by laspy. Each repeat:

* alone: laspy reads the file in chunks (the backend and chunk size the index build uses), then
  ``open_map`` builds its index in a fresh cache folder;
* beside a live pipeline: the docs' first example (``source: synthetic`` at its default 100,000
  points a scan, 10 Hz, the cpu tier) with the file as its ``map:`` and a fresh cache folder;
  while the map stage builds the index, another process reads the same file with laspy in a
  loop. The map stage's build time (``map_open_s``) against those reads' median.

Fair share: the build's time over laspy's read time is about the same beside the pipeline as
alone (a build starved by the live stages would take many more reads' time). Also written:
when the first map points (the preview) were drawn, from the first frame.

    PYTHONPATH=$PWD .venv/bin/python bench/bench_map_share.py --repeats 2

Writes ``bench/results/map_share.json``.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

import _harness as H
from pointflow import Pipeline

N = 697_721
READER = """
import sys, time, laspy
from pointflow import formats
from pointflow.map.inputs import CHUNK_POINTS
path, stop = sys.argv[1], sys.argv[2]
import os
while not os.path.exists(stop):
    t = time.monotonic()
    with laspy.open(path, laz_backend=formats.las.laz_backend()) as f:
        for _ in f.chunk_iterator(CHUNK_POINTS):
            pass
    print(time.monotonic() - t, flush=True)
"""


def utm_file(out: str) -> str:
    import laspy

    src = laspy.read(str(H.DATA / "autzen_trim.laz"))
    x, y, z = (np.asarray(v) * 0.3048 for v in (src.x, src.y, src.z))  # international feet -> metres
    x, y = x - x.min(), y - y.min()
    w, h = x.max() + 1, y.max() + 1
    X = np.concatenate([x + (i % 4) * w for i in range(7)])[:N] + 512_000.0
    Y = np.concatenate([y + (i // 4) * h for i in range(7)])[:N] + 6_600_000.0
    hdr = laspy.LasHeader(point_format=3, version="1.2")
    hdr.scales, hdr.offsets = [0.01, 0.01, 0.01], [512_000.0, 6_600_000.0, 0.0]
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = X, Y, np.concatenate([z] * 7)[:N]
    las.intensity = np.concatenate([np.asarray(src.intensity)] * 7)[:N]
    las.write(out, laz_backend=laspy.LazBackend.Lazrs)
    return out


def read_s(path: str) -> float:
    import laspy

    from pointflow import formats
    from pointflow.map.inputs import CHUNK_POINTS

    t = time.monotonic()
    with laspy.open(path, laz_backend=formats.las.laz_backend()) as f:
        for _ in f.chunk_iterator(CHUNK_POINTS):
            pass
    return time.monotonic() - t


def alone(path: str, tmp: str) -> dict:
    from pointflow.map import open_map

    r = read_s(path)
    t = time.monotonic()
    open_map(path, cache_dir=tempfile.mkdtemp(dir=tmp), progress=False).close()
    b = time.monotonic() - t
    return {"read_s": round(r, 3), "build_s": round(b, 3), "build_over_read": round(b / r, 2)}


def beside(path: str, tmp: str) -> dict:
    cfg = {"source": {"transport": "synthetic"},
           "render": {"backend": "cpu", "size": [960, 540], "output": {"every_n_frames": 1_000_000}},
           "map": {"path": path, "cache_dir": tempfile.mkdtemp(dir=tmp)}}
    stop = os.path.join(tmp, f"stop-{time.monotonic_ns()}")
    env = dict(os.environ)
    with Pipeline.from_dict(cfg, out_dir=tempfile.mkdtemp(dir=tmp)) as pipe:
        reader = subprocess.Popen([sys.executable, "-c", READER, path, stop], stdout=subprocess.PIPE, text=True,
                                  env=env)
        t_frame = t_map = None
        end = time.monotonic() + 300
        while time.monotonic() < end:
            st = pipe.stats()["stages"]
            ren, mp = st.get("render", {}), st.get("map", {})
            now = time.monotonic()
            if t_frame is None and (ren.get("frames") or 0) > 0:
                t_frame = now
            if t_map is None and (ren.get("map_points") or 0) > 0:
                t_map = now
            if mp.get("map_ready") and t_map is not None:
                break
            time.sleep(0.05)
        open(stop, "w").close()
        reads = [float(v) for v in reader.communicate(timeout=120)[0].split()]
        mp = pipe.stats()["stages"]["map"]
        build = mp.get("map_open_s")
        cpu = mp.get("cpu_percent")
    med = float(np.median(reads)) if reads else None
    return {"build_s": build, "reads_s": [round(v, 3) for v in reads], "read_s_median": round(med, 3) if med else None,
            "build_over_read": round(build / med, 2) if build and med else None, "map_cpu_percent_last": cpu,
            "first_map_points_after_first_frame_s": round(t_map - t_frame, 3) if t_map and t_frame else None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--out", default=str(H.RESULTS / "map_share.json"))
    a = ap.parse_args()
    tmp = tempfile.mkdtemp(prefix="bench-map-share-")
    res: dict = {"machine": H.machine(command=H.command()), "args": vars(a)}
    path = utm_file(os.path.join(tmp, "utm_697721.laz"))
    res["runs"] = []
    for i in range(a.repeats):
        run = {"alone": alone(path, tmp), "beside_pipeline": beside(path, tmp)}
        print(run, flush=True)
        res["runs"].append(run)
    al = [r["alone"]["build_over_read"] for r in res["runs"]]
    bs = [r["beside_pipeline"]["build_over_read"] for r in res["runs"] if r["beside_pipeline"]["build_over_read"]]
    res["median_build_over_read"] = {"alone": float(np.median(al)), "beside_pipeline": float(np.median(bs)) if bs else None}
    H.machine_done(res["machine"])
    H.write_result(a.out, res)
    print(res["median_build_over_read"])


if __name__ == "__main__":
    main()
