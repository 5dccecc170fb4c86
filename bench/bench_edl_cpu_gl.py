"""Eye-dome lighting cost in the cpu and gl tiers, and cpu-tier pictures with and without it.

For each scene and tier, two renderers (``render.edl`` off and on) draw the same static
frame in alternation (order flipped every round), after a warm-up; a frame is render +
read_image, as in bench_tiers.py. Reported: median ms off / on and their ratio (same run,
interleaved, so load on a shared machine hits both alike).

    .venv/bin/python bench/bench_edl_cpu_gl.py              # ~3 min here
    .venv/bin/python bench/bench_edl_cpu_gl.py --pictures   # also bench/results/edl_cpu_*.png

Output: a table on stdout and ``bench/results/edl_cpu_gl.json``. The wgpu tier's EDL
figures are bench_render.py's.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time

import numpy as np

import _harness as H
from _harness.scenes import scene_autzen, scene_demo, scene_dense
from pointflow.config import EdlConfig, RenderConfig
from pointflow.render.cpu import CpuRenderer

RESULTS = H.RESULTS


def make(tier: str, cfg: RenderConfig, n: int):
    if tier == "cpu":
        return CpuRenderer(cfg, n, ["intensity"])
    from pointflow.render.gl import GlRenderer
    return GlRenderer(cfg, n, ["intensity"])


def frame_ms(r, frame, cam) -> float:
    t0 = time.perf_counter()
    r.render(frame, cam)
    r.read_image()
    return (time.perf_counter() - t0) * 1e3


def measure(tier: str, frame, cam, size, rounds: int) -> dict:
    base = RenderConfig(size=list(size), color_by="intensity", point_size=2,
                        color_range=list(frame.channel_ranges["intensity"]))
    rs = {k: make(tier, dataclasses.replace(base, edl=EdlConfig(enabled=k == "on")), frame.size)
          for k in ("off", "on")}
    try:
        for r in rs.values():  # warm-up: uploads, shader compiles, allocations
            frame_ms(r, frame, cam)
        ts = H.interleave({k: (lambda k=k: frame_ms(rs[k], frame, cam)) for k in ("off", "on")}, rounds)
    finally:
        for r in rs.values():
            r.close()
    off, on = float(np.median(ts["off"])), float(np.median(ts["on"]))
    return {"off_ms": off, "on_ms": on, "ratio": on / off, "rounds": rounds, "samples": ts}


def pass_cost(tier: str, size, rounds: int, frame, cam) -> dict:
    """The EDL pass alone, at ``size``: cpu — the tier's own ``edl`` timing (rules.edl_shade
    + apply_shade) over ``frame``'s winners; gl — an empty frame with EDL on minus off
    (the post pass is per pixel, independent of the points), interleaved medians."""
    base = RenderConfig(size=list(size), color_by="intensity", point_size=2,
                        color_range=list(frame.channel_ranges["intensity"]))
    if tier == "cpu":
        r = make("cpu", dataclasses.replace(base, edl=EdlConfig(enabled=True)), frame.size)
        ts = [r.render(frame, cam).timings_ms["edl"] for _ in range(rounds)]
        return {"edl_pass_ms": float(np.median(ts)), "samples": ts}
    empty = dataclasses.replace(frame, size=0)
    rs = {k: make(tier, dataclasses.replace(base, edl=EdlConfig(enabled=k == "on")), frame.size) for k in ("off", "on")}
    try:
        for r in rs.values():
            frame_ms(r, empty, cam)
        ts = H.interleave({k: (lambda k=k: frame_ms(rs[k], empty, cam)) for k in ("off", "on")}, rounds)
    finally:
        for r in rs.values():
            r.close()
    return {"edl_pass_ms": float(np.median(ts["on"]) - np.median(ts["off"])), "samples": ts}


def pictures(scenes: dict, size) -> list[str]:
    from pointflow.render.process import write_png

    out = []
    for key, (frame, cam, desc) in scenes.items():
        base = RenderConfig(size=list(size), color_by="intensity", point_size=2,
                            color_range=list(frame.channel_ranges["intensity"]))
        imgs = []
        for on in (False, True):
            r = CpuRenderer(dataclasses.replace(base, edl=EdlConfig(enabled=on)), frame.size, ["intensity"])
            r.render(frame, cam)
            imgs.append(r.read_image())
        gap = np.zeros((size[1], 6, 4), np.uint8)
        gap[..., 3] = 255
        path = RESULTS / f"edl_cpu_{key}.png"
        write_png(str(path), np.concatenate([imgs[0], gap, imgs[1]], axis=1))
        out.append(str(path))
        print(f"wrote {path} ({desc}: EDL off | on)")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="1280x720")
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--tiers", default="cpu,gl")
    ap.add_argument("--pictures", action="store_true", help="write cpu-tier EDL off|on pictures (960x540 each)")
    ap.add_argument("--scenes", default="demo,dense_1m,autzen")
    a = ap.parse_args(argv)
    size = tuple(int(v) for v in a.size.split("x"))
    aspect = size[0] / size[1]
    want = a.scenes.split(",")
    machine = H.machine(numpy=np.__version__)
    scenes = {"demo": scene_demo(aspect, 300_000)}
    if "dense_1m" in want:
        scenes["dense_1m"] = scene_dense(aspect, 1_000_000)
    autzen = scene_autzen(aspect) if "autzen" in want else None
    if autzen is not None:
        scenes["autzen"] = autzen
    rows = []
    print(f"{'scene':34} {'tier':5} {'EDL off ms':>10} {'EDL on ms':>10} {'on/off':>7}")
    for key, (frame, cam, desc) in scenes.items():
        if key not in want:
            continue
        for tier in a.tiers.split(","):
            m = measure(tier, frame, cam, size, a.rounds)
            rows.append({"scene": key, "scene_desc": desc, "tier": tier, **m})
            print(f"{desc:34} {tier:5} {m['off_ms']:10.1f} {m['on_ms']:10.1f} {m['ratio']:7.3f}")
    passes = {}
    frame, cam, _ = scenes["demo"]
    for tier in a.tiers.split(","):
        passes[tier] = pass_cost(tier, size, 3 * a.rounds, frame, cam)
        print(f"EDL pass alone at {size[0]}x{size[1]}, {tier}: {passes[tier]['edl_pass_ms']:.1f} ms")
    out = {"edl_pass": passes, "machine": H.machine_done(machine), "command": H.command(),
           "size": list(size), "edl": dataclasses.asdict(EdlConfig(enabled=True)), "rows": rows}
    H.write_result(RESULTS / "edl_cpu_gl.json", out, indent=1)
    if a.pictures:
        pics = {k: v for k, v in scenes.items() if k in ("demo", "autzen")}
        pictures(pics, (960, 540))
    return 0


if __name__ == "__main__":
    sys.exit(main())
