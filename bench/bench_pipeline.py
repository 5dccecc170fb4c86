"""Frames per second of the full pipeline (``configs/demo.yaml``, 1M-point ring) per raster method.

Runs the real pipeline (synthetic lidar 100k points/scan at 10 scans/s → ingest → ring →
cadence → render) once per method and round, alternating ``render.raster: quads`` and
``compute`` so both see the same machine load; after a warm-up that fills the 1M ring, the
render stage's frames are counted between two stats samples. PNG output is off (it is not
part of the render rate).

    XDG_RUNTIME_DIR=/tmp/xdg .venv/bin/python bench/bench_pipeline.py [--seconds 8] [--rounds 2]

Writes ``bench/results/pipeline_raster.json``. ``--auto`` instead compares ``backend: auto``
(which picks the compiled cpu raster over a software adapter where it measured faster) with
what ``auto`` drew before it existed, ``backend: wgpu, raster: compute`` (issue 29), and writes
``bench/results/pipeline_auto.json``.
"""
from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import yaml

import _harness as H
from _harness.pipeline import stats_window

ROOT = H.ROOT


def run_once(raster: str, seconds: float, warmup_s: float, backend: str = "auto") -> dict:
    cfg = yaml.safe_load((ROOT / "configs" / "demo.yaml").read_text())
    cfg["render"]["raster"] = raster
    cfg["render"]["backend"] = backend
    cfg["render"]["output"] = {"dir": None}
    cfg.setdefault("supervisor", {})["hung_after_ms"] = 10000
    s0, s1 = stats_window(cfg, seconds, warmup_s, f"raster {raster}")
    r1 = s1["stages"].get("render", {})
    frames = s1["frames"] - s0["frames"]
    dt = max(s1["elapsed_s"] - s0["elapsed_s"], 1e-9)
    info = r1.get("tier_info") or {}
    return {"raster": raster, "fps": frames / dt, "frames": frames, "seconds": dt, "tier": r1.get("tier"),
            "raster_used": info.get("raster"), "compute_keys": info.get("compute_keys"),
            "ring_points": s1["stages"].get("ingest", {}).get("ring_size")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--warmup", type=float, default=12.0, help="fills the 1M ring (1M points/s)")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--out", default=str(H.RESULTS / "pipeline_raster.json"))
    ap.add_argument("--auto", action="store_true",
                    help="backend: auto against backend: wgpu, raster: compute (bench/results/pipeline_auto.json)")
    a = ap.parse_args()
    if a.auto:
        return compare_auto(a)
    runs = []
    machine = H.machine()
    for r in range(a.rounds):
        for raster in H.order(("quads", "compute"), r):
            res = run_once(raster, a.seconds, a.warmup)
            runs.append(res)
            print(f"  round {r + 1} {raster:8}: {res['fps']:6.2f} frames/s ({res['frames']} frames in "
                  f"{res['seconds']:.1f} s; tier {res['tier']}, raster {res['raster_used']})", flush=True)
    med = {m: statistics.median(x["fps"] for x in runs if x["raster"] == m) for m in ("quads", "compute")}
    print(f"median frames/s: quads {med['quads']:.2f}, compute {med['compute']:.2f} "
          f"(x{med['compute'] / max(med['quads'], 1e-9):.2f})")
    H.write_result(a.out, {"config": "configs/demo.yaml (1M ring, 1280x720, 2 px, intensity)", "runs": runs,
                           "median_fps": med, "machine": H.machine_done(machine), "command": H.command()}, indent=1)


def compare_auto(a) -> None:
    """``backend: auto`` (today's selection) against ``wgpu`` + ``compute`` (before issue 29),
    alternating per round so both see the same load."""
    kinds = {"auto": ("auto", "auto"), "wgpu_compute": ("wgpu", "compute")}
    runs = []
    machine = H.machine()
    for r in range(a.rounds):
        for k in H.order(list(kinds), r):
            backend, raster = kinds[k]
            res = run_once(raster, a.seconds, a.warmup, backend=backend)
            res["kind"] = k
            runs.append(res)
            print(f"  round {r + 1} {k:13}: {res['fps']:6.2f} frames/s ({res['frames']} frames in "
                  f"{res['seconds']:.1f} s; tier {res['tier']}, raster {res['raster_used']})", flush=True)
    med = {k: statistics.median(x["fps"] for x in runs if x["kind"] == k) for k in kinds}
    print(f"median frames/s: backend auto {med['auto']:.2f}, wgpu compute {med['wgpu_compute']:.2f} "
          f"(x{med['auto'] / max(med['wgpu_compute'], 1e-9):.2f})")
    out = Path(a.out if a.out != str(H.RESULTS / "pipeline_raster.json") else H.RESULTS / "pipeline_auto.json")
    H.write_result(out, {"config": "configs/demo.yaml (1M ring, 1280x720, 2 px, intensity)", "runs": runs,
                         "median_fps": med, "machine": H.machine_done(machine), "command": H.command()}, indent=1)


if __name__ == "__main__":
    main()
