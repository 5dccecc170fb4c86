"""Speed versus accuracy of the render tiers and their point-saving methods, and the cpu crossover.

Reference: the cpu tier drawing every point (float64 projection). For each scene, tier (the
wgpu tier once per raster method: ``wgpu-quads``, ``wgpu-compute``) and
method (full; LOD stride 2/4/8; importance sampling at budgets of 5/10/25/50/100%; time
windows keeping the newest 10/25/50%) it measures the median frame time and the image
error against the reference: PSNR (RGB), the fraction of pixels that differ, and the IoU
of lit pixels. Then it times the three tiers on growing scenes to find the crossover size
below which the cpu tier is faster (written to ``bench/results/crossover.json`` and, unless
``--install`` is given, to the user cache that ``select_renderer`` reads).

    .venv/bin/python bench/bench_tiers.py            # ~2-4 min on 2 cores
    .venv/bin/python bench/bench_tiers.py --quick    # fewer scenes/sizes
    .venv/bin/python bench/bench_tiers.py --chart-only   # redraw tiers.png from tiers.json

The autzen and Ouster scenes come from ``../shared/data`` beside the checkout (env
``POINTFLOW_DATA`` overrides; skipped when absent).

Output: a table on stdout, ``bench/results/tiers.json``, ``bench/results/tiers.png``
(frame time vs error, one point per run, the Pareto front numbered), ``crossover.json``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Optional

import numpy as np

import _harness as H
from _harness.scenes import scene_autzen, scene_demo, scene_dense, scene_ouster
from _harness.tiers import errors, make_tier
from pointflow.config import RenderConfig
from pointflow.render.base import FrameInput, Renderer
from pointflow.render.camera import Camera
from pointflow.render.cpu import CpuRenderer
from pointflow.render.rules import importance_range_for_budget

RESULTS = H.RESULTS


# ----------------------------------------------------------------------------- methods
def methods(n: int, now_ms: float, span_ms: float) -> list[tuple[str, str, float, dict, Optional[int]]]:
    """(family, label, x, render-config overrides, budget)."""
    out = [("full", "full", 1.0, {}, None)]
    for s in (2, 4, 8):
        out.append(("lod", f"lod {s}", 1.0 / s, {"lod_stride": s}, None))
    for p in (0.05, 0.10, 0.25, 0.50, 1.00):
        out.append(("importance", f"imp {p:.0%}", p, {"importance_sampling": True}, int(n * p)))
    for p in (0.10, 0.25, 0.50):
        out.append(("time window", f"window {p:.0%}", p, {"time_window_ms": max(span_ms * p, 1e-3)}, None))
    return out


def timed(r: Renderer, frame: FrameInput, cam: Camera, repeats: int) -> tuple[float, np.ndarray]:
    """Median frame time (ms): render + finish + read back, after one warm-up frame."""
    frame.dirty = None
    r.render(frame, cam)
    r.read_image()
    frame.dirty = []  # static scene: nothing new to upload after the first frame
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        r.render(frame, cam)
        img = r.read_image()
        ts.append((time.perf_counter() - t0) * 1e3)
    frame.dirty = None
    return float(np.median(ts)), img


def pareto(points: list[tuple[float, float]]) -> list[int]:
    """Indices of non-dominated (time, error) points, by increasing time."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], float("inf")
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


# ----------------------------------------------------------------------------- runs
def accuracy_runs(scenes, tiers, size, repeats) -> list[dict]:
    rows = []
    for key, (frame, cam, desc) in scenes.items():
        n = frame.size
        print(f"\n== {key}: {desc} at {size[0]}x{size[1]}")
        base = dict(size=list(size), color_by="intensity", point_size=2,
                    color_range=list(frame.channel_ranges["intensity"]))
        ref_cfg = RenderConfig(**base)
        ref_r = CpuRenderer(ref_cfg, n, ["intensity"])
        ref_r.render(frame, cam)
        ref = ref_r.read_image()
        bg = ref[0, 0].copy()
        span = float(frame.t_ingest_ms.max() - frame.t_ingest_ms.min())
        print(f"{'tier':12} {'method':12} {'ms':>8} {'x ref':>6} {'PSNR dB':>8} {'diff %':>7} {'IoU':>6}")
        for tier in tiers:
            full_ms = None
            for fam, label, frac, over, budget in methods(n, frame.now_ms, span):
                cfg = RenderConfig(**{**base, **over})
                r = make_tier(tier, cfg, n)
                if r is None:
                    break
                frame.budget = budget if budget is not None and budget < n else None
                frame.frame_seed = 1
                ranges = dict(frame.channel_ranges)
                if fam == "importance":  # scale the sampling so it aims at the budget (see cpu.py)
                    lo, hi = ranges["importance"]
                    frame.channel_ranges["importance"] = importance_range_for_budget(frame.importance, lo, hi, budget)
                try:
                    ms, img = timed(r, frame, cam, repeats)
                finally:
                    r.close()
                    frame.budget = None
                    frame.channel_ranges = ranges
                e = errors(img, ref, bg)
                full_ms = full_ms or ms
                rows.append({"scene": key, "scene_desc": desc, "points": n, "tier": tier, "family": fam,
                             "method": label, "fraction": frac, "frame_ms": ms, **e})
                print(f"{tier:12} {label:12} {ms:8.1f} {ms / full_ms:6.2f} {e['psnr_db']:8.2f} "
                      f"{100 * e['diff_fraction']:7.2f} {e['coverage_iou']:6.3f}")
    return rows


def crossover_runs(tiers, size, sizes, repeats) -> dict:
    print(f"\n== crossover: frame time vs points at {size[0]}x{size[1]} (full render, static scene)")
    res: dict[str, dict[int, float]] = {t: {} for t in tiers}
    for n in sizes:
        frame, cam, _ = scene_dense(size[0] / size[1], n)
        cfg = RenderConfig(size=list(size), color_by="intensity", point_size=2, color_range=[0.0, 1.0])
        line = f"{n:>9,}"
        for tier in tiers:
            r = make_tier(tier, cfg, n)
            if r is None:
                continue
            try:
                ms, _ = timed(r, frame, cam, repeats)
            finally:
                r.close()
            res[tier][n] = ms
            line += f"  {tier} {ms:8.1f} ms"
        print(line)
    xo_points, verdict, cpu_from = crossover_from(res, sizes)
    print(f"crossover: {xo_points:,} points ({verdict})")
    return {"crossover_points": xo_points, "verdict": verdict, "cpu_faster_from": cpu_from, "size": list(size),
            "frame_ms": {t: {str(k): v for k, v in d.items()} for t, d in res.items()}}


def crossover_from(res: dict[str, dict[int, float]], sizes: list[int]) -> tuple[int, str, Optional[int]]:
    """(crossover, verdict, cpu_faster_from) for select's rule "cpu below the crossover":
    the crossover is the largest measured size n such that the cpu tier beat the best GPU
    tier at every measured size <= n (0 when a GPU tier already wins at the smallest
    size). ``cpu_faster_from`` is the smallest size from which the cpu tier wins at every
    larger size (software adapters), or None."""
    gpu = [t for t in res if t != "cpu" and res[t]]
    best = {n: min(res[t][n] for t in gpu if n in res[t]) for n in sizes if any(n in res[t] for t in gpu)}
    cpu = res.get("cpu", {})
    wins = [n for n in sorted(best) if n in cpu and cpu[n] < best[n]]
    xo = 0
    for n in sorted(best):
        if n in cpu and cpu[n] < best[n]:
            xo = n
        else:
            break
    cpu_from = None
    for n in sorted(best, reverse=True):
        if n in cpu and cpu[n] < best[n]:
            cpu_from = n
        else:
            break
    verdict = (f"cpu tier faster up to {xo:,} points" if xo else "a GPU tier is faster at the smallest size measured")
    if cpu_from is not None and cpu_from > xo:
        verdict += f"; the cpu tier is faster again from {cpu_from:,} points up (software GPU adapters)"
    del wins
    return xo, verdict, cpu_from


#: floor for the log error axis: the reference itself has error 0 (drawn on this line, "exact")
_EXACT = 3e-6
_TIER_COLOURS = {"cpu": "tab:blue", "cpu-compute": "tab:purple", "gl": "tab:orange", "wgpu": "tab:green", "wgpu-quads": "tab:green",
                 "wgpu-compute": "tab:red"}
_FAMILY_MARKERS = {"full": "*", "lod": "s", "importance": "o", "time window": "^"}


def chart(rows: list[dict], path: Path) -> None:
    """One panel per scene: every (tier, method) run as a point (colour = tier, marker =
    method family), no connecting lines; the Pareto front (nothing else is both faster and
    closer to the reference) as a step line with its points ringed and labelled; legends
    outside the panels."""
    if (plt := H.pyplot()) is None:
        return
    import matplotlib.ticker
    from matplotlib.lines import Line2D

    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    cols = 2 if len(scenes) > 1 else 1
    nrows = (len(scenes) + cols - 1) // cols
    fig, axs = plt.subplots(nrows, cols, figsize=(6.4 * cols + 2.6, 4.6 * nrows), squeeze=False)
    tiers = list(dict.fromkeys(r["tier"] for r in rows))
    for ax, sc in zip(axs.ravel(), scenes):
        rs = [r for r in rows if r["scene"] == sc]
        pts = [(r["frame_ms"], max(r["diff_fraction"], _EXACT)) for r in rs]
        front = pareto(pts)
        on_front = set(front)
        for i, r in enumerate(rs):
            big = 1.8 if r["family"] == "full" else 1.0  # a star reads smaller than a disc
            ax.scatter(*pts[i], marker=_FAMILY_MARKERS.get(r["family"], "x"), s=(75 if i in on_front else 30) * big,
                       color=_TIER_COLOURS.get(r["tier"], "grey"), alpha=1.0 if i in on_front else 0.35,
                       edgecolors="black" if i in on_front else "none", linewidths=0.9, zorder=3 if i in on_front else 2)
        fx = [pts[i][0] for i in front]
        fy = [pts[i][1] for i in front]
        ax.step(fx, fy, where="post", color="black", lw=1.2, alpha=0.6, zorder=1)
        placed: list[int] = []
        for k, i in enumerate(front):  # numbers on the front; nearby ones stack upwards
            j = sum(1 for q in placed if 1 / 1.5 < pts[q][0] / pts[i][0] < 1.5 and 1 / 2.5 < pts[q][1] / pts[i][1] < 2.5)
            placed.append(i)
            ax.annotate(str(k + 1), pts[i], xytext=(5 + 7 * j, 5 + 9 * j), textcoords="offset points",
                        fontsize=8, fontweight="bold", zorder=4)
        key = [f"{k + 1}  {rs[i]['tier']} {rs[i]['method']}: {rs[i]['frame_ms']:.0f} ms, "
               f"{100 * rs[i]['diff_fraction']:.2g}%" for k, i in enumerate(front)]
        half = (len(key) + 1) // 2
        for col, lines in ((0.015, key[:half]), (0.515, key[half:])):
            ax.text(col, 0.975, "\n".join(lines), transform=ax.transAxes, va="top", ha="left", fontsize=7.5,
                    bbox=dict(boxstyle="round,pad=0.3", fc="white", ec="lightgrey", alpha=0.9) if lines else None)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_ylim(_EXACT / 2, 100.0)  # the band above 1 holds the key to the numbered front
        ax.set_yticks([10.0 ** e for e in range(-5, 1)])
        ax.axhline(_EXACT, color="grey", lw=0.6, ls=":")
        ax.text(0.01, _EXACT * 1.25, "exact (the reference)", transform=ax.get_yaxis_transform(), ha="left",
                fontsize=7, color="grey")
        ax.xaxis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel("frame time, ms (log)")
        ax.set_ylabel("fraction of pixels differing\nfrom the float64 reference (log)")
        ax.set_title(rs[0]["scene_desc"], fontsize=9.5)
        ax.grid(True, which="major", alpha=0.3)
    for ax in axs.ravel()[len(scenes):]:
        ax.set_visible(False)
    tier_h = [Line2D([], [], ls="", marker="o", color=_TIER_COLOURS.get(t, "grey"), label=t) for t in tiers]
    fam_h = [Line2D([], [], ls="", marker=m, color="dimgrey", label=f) for f, m in _FAMILY_MARKERS.items()]
    front_h = [Line2D([], [], color="black", alpha=0.6, marker="o", mfc="white", mec="black",
                      label="Pareto front (ringed,\nnumbered, key on top:\nframe ms, pixels differing)")]
    fig.tight_layout(rect=(0, 0, (6.4 * cols) / (6.4 * cols + 2.6), 1))
    x0 = (6.4 * cols) / (6.4 * cols + 2.6) + 0.01
    leg = fig.legend(handles=tier_h, title="tier (colour)", loc="upper left", bbox_to_anchor=(x0, 0.95), fontsize=8.5)
    fig.add_artist(leg)
    leg2 = fig.legend(handles=fam_h, title="method (marker)", loc="upper left", bbox_to_anchor=(x0, 0.70),
                      fontsize=8.5)
    fig.add_artist(leg2)
    fig.legend(handles=front_h, loc="upper left", bbox_to_anchor=(x0, 0.45), fontsize=8.5)
    fig.text(x0, 0.30, "faded: not on the front\n(something else is both\nfaster and closer to\nthe reference)",
             fontsize=8, color="dimgrey", va="top")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer scenes and sizes")
    ap.add_argument("--tiers", default="cpu,gl,wgpu-quads,wgpu-compute",
                    help="cpu, gl, wgpu (its auto raster method), wgpu-quads, wgpu-compute")
    ap.add_argument("--size", default="960x540")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--install", action="store_true",
                    help="also write the crossover to the user cache that select_renderer reads")
    ap.add_argument("--skip-crossover", action="store_true",
                    help="keep the crossover figures of the existing tiers.json (and crossover.json)")
    ap.add_argument("--chart-only", action="store_true", help="redraw tiers.png from tiers.json, run nothing")
    ap.add_argument("--merge", action="store_true",
                    help="run only --tiers on the accuracy scenes and replace those tiers' rows (per scene) in the existing "
                         "tiers.json (the other rows keep their older timings; say so where quoted)")
    a = ap.parse_args(argv)
    if a.chart_only:
        chart(json.loads((RESULTS / "tiers.json").read_text())["rows"], RESULTS / "tiers.png")
        print(f"wrote {RESULTS / 'tiers.png'}")
        return 0
    size = tuple(int(v) for v in a.size.split("x"))
    tiers = [t for t in a.tiers.split(",") if t]
    aspect = size[0] / size[1]
    RESULTS.mkdir(parents=True, exist_ok=True)
    machine = H.machine(numpy=np.__version__)
    scenes = {"demo": scene_demo(aspect, 100_000 if a.quick else 300_000),
              "dense": scene_dense(aspect, 150_000 if a.quick else 400_000)}
    if not a.quick:
        for key, fn in (("autzen", scene_autzen), ("ouster", scene_ouster)):
            s = fn(aspect)
            if s is not None:
                scenes[key] = s
    rows = accuracy_runs(scenes, tiers, size, a.repeats)
    if a.merge:
        old = json.loads((RESULTS / "tiers.json").read_text())
        stamp = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        for r in rows:
            r["measured_at"] = stamp
        done = {(r["tier"], r["scene"]) for r in rows}
        old["rows"] = [r for r in old["rows"] if (r["tier"], r["scene"]) not in done] + rows
        old.setdefault("merged", []).append({"tiers": tiers, "at": stamp, "scenes": list(scenes),
                                             "machine": H.machine_done(machine)})
        (RESULTS / "tiers.json").write_text(json.dumps(old, indent=1))
        chart(old["rows"], RESULTS / "tiers.png")
        print(f"\nmerged {tiers} into {RESULTS / 'tiers.json'}; wrote {RESULTS / 'tiers.png'}")
        return 0
    out = {"machine": machine, "command": H.command(),
           "size": list(size), "repeats": a.repeats, "reference": "cpu tier, every point, float64 projection",
           "rows": rows}
    if a.skip_crossover and (RESULTS / "tiers.json").exists():
        old = json.loads((RESULTS / "tiers.json").read_text())
        if "crossover" in old:
            out["crossover"] = old["crossover"]
    if not a.skip_crossover:
        sizes = [1_000, 10_000, 30_000, 100_000, 300_000] if a.quick else [1_000, 3_000, 10_000, 30_000, 100_000, 300_000, 1_000_000]
        xo = crossover_runs(tiers, (1280, 720), sizes, a.repeats)
        H.machine_done(machine)
        out["crossover"] = xo
        blob = json.dumps({"crossover_points": xo["crossover_points"], "verdict": xo["verdict"],
                           "measured": time.strftime("%Y-%m-%d"), "machine": out["machine"]}, indent=1)
        (RESULTS / "crossover.json").write_text(blob)
        if a.install:
            from pointflow.render.select import cache_path
            p = cache_path()
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_text(blob)
            print(f"crossover written to {p}")
    H.machine_done(machine)
    H.write_result(RESULTS / "tiers.json", out, indent=1)
    chart(rows, RESULTS / "tiers.png")
    print(f"\nwrote {RESULTS / 'tiers.json'}, {RESULTS / 'tiers.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
