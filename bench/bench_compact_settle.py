"""Compact positions settling (issue 41, wave 5h) on a ring that stops changing: the wgpu
compute method with compact positions on, the scene of ``bench_cpu_threads.py`` (the autzen
tile repeated to N points, 1280x720, 2 px squares, turbo by intensity), the whole ring written
once and then drawn unchanged. Per frame the CPU side (``cpu_total``), the batches encoded so
far, the bytes uploaded and the position bytes read per point: what settling costs while it
encodes (at most ``compact.ENCODE_POINTS_PER_FRAME`` points a frame) and what a settled
ring's frame costs after.

    PYTHONPATH=$PWD .venv/bin/python bench/bench_compact_settle.py --points 1000000

Writes ``bench/results/compact_settle.json``.
"""
from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace
from typing import Optional

import numpy as np

import _harness
from _harness.scenes import H, W, tiled_scene


def run(n: int, settle: int, frames: int) -> dict:
    os.environ["POINTFLOW_WGPU_COMPACT"] = "1"
    os.environ["POINTFLOW_WGPU_COMPACT_SETTLE"] = str(settle)
    from pointflow.config import RenderConfig
    from pointflow.render.wgpu_tier import WgpuRenderer
    from pointflow.render.wgpu_tier.compact import ENCODE_POINTS_PER_FRAME
    machine = _harness.machine()
    f, cam = tiled_scene(n)
    cfg = RenderConfig(size=[W, H], color_by="intensity", colormap="turbo", point_size=2.0, gpu_timestamps=False,
                       backend="wgpu", raster="compute")
    r = WgpuRenderer(replace(cfg), n, ["intensity"])
    rows = []
    try:
        f.dirty = None
        for i in range(frames):
            st = r.render(f, cam)
            r.read_image()
            f.dirty = []
            rows.append({"frame": i, "cpu_side_ms": st.timings_ms["cpu_total"],
                         "encoded_batches": st.extra.get("compact_encoded_batches"),
                         "uploaded_bytes": st.uploaded_bytes,
                         "position_bytes_per_point": st.extra.get("compact_position_bytes_per_point")})
            print(f"frame {i:3d}  cpu side {rows[-1]['cpu_side_ms']:8.2f} ms  encoded {rows[-1]['encoded_batches']:5d}"
                  f"  uploaded {st.uploaded_bytes:10,d} B  {rows[-1]['position_bytes_per_point']:.2f} B/point",
                  flush=True)
    finally:
        r.close()
    last = rows[-1]["encoded_batches"]
    encoding = [x["cpu_side_ms"] for x in rows[1:] if x["uploaded_bytes"] > 0]
    settled = [x["cpu_side_ms"] for x in rows if x["encoded_batches"] == last and x["uploaded_bytes"] == 0]
    return {"points": n, "settle_frames": settle, "encode_points_per_frame": ENCODE_POINTS_PER_FRAME,
            "frames": rows, "encoding_frames": len(encoding),
            "encoding_cpu_side_median_ms": float(np.median(encoding)) if encoding else None,
            "settled_cpu_side_median_ms": float(np.median(settled[2:])) if len(settled) > 2 else None,
            "machine": _harness.machine_done(machine),
            "measured_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "command": _harness.command()}


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--settle", type=int, default=3, help="POINTFLOW_WGPU_COMPACT_SETTLE for the run")
    ap.add_argument("--frames", type=int, default=0, help="frames drawn (default: enough to settle, +12)")
    ap.add_argument("--out", default=str(_harness.RESULTS / "compact_settle.json"))
    a = ap.parse_args(argv)
    from pointflow.render.wgpu_tier.compact import ENCODE_POINTS_PER_FRAME
    frames = a.frames or a.settle + 2 + -(-a.points // ENCODE_POINTS_PER_FRAME) + 12
    res = run(a.points, a.settle, frames)
    print(f"encoding: {res['encoding_frames']} frames, CPU side median {res['encoding_cpu_side_median_ms']} ms; "
          f"settled: CPU side median {res['settled_cpu_side_median_ms']} ms", flush=True)
    _harness.write_result(a.out, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
