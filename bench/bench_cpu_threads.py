"""The compiled cpu raster against its thread count (issue 41): frame time at 1..N numba
threads for each way of sharing the work (``auto``, ``bins``, ``points``; the env
``POINTFLOW_CPU_RASTER_SPLIT`` of :mod:`pointflow.render.cpu_compute`), frames interleaved in
rotating order so that every (split, threads) pair sees the same load; the scene of
``bench_render.py --cpu-raster`` (the autzen tile repeated to N points, 1280x720, 2 px
squares, turbo by intensity, 1% of the ring rewritten per frame, output = read_image):

    PYTHONPATH=$PWD .venv/bin/python bench/bench_cpu_threads.py --sizes 100000 1000000
    NUMBA_NUM_THREADS=4 PYTHONPATH=$PWD .venv/bin/python bench/bench_cpu_threads.py   # up to 4 threads

N is numba's thread count (``NUMBA_NUM_THREADS``, default the cores). Per pair: the median wall
time and process CPU time per frame; per split the speed-up at t threads = the median of the
per-round ratios (1-thread frame / t-thread frame of the same round), so load that changes
between rounds cancels. Writes ``bench/results/cpu_threads.json`` and the chart ``.png``.
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
from _harness.scenes import H, W, base_cloud, camera_for, make_frame, tiled
from pointflow.config import RenderConfig

SPLITS = ("auto", "bins", "points")


def measure(sizes: list[int], rounds: int, splits: tuple[str, ...]) -> dict[str, Any]:
    import numba

    from pointflow.render.cpu_compute import CpuComputeRenderer
    machine = _harness.machine()
    most = int(numba.config.NUMBA_NUM_THREADS)
    threads = list(range(1, most + 1))
    base, inten0, scene = base_cloud()
    cfg = RenderConfig(size=[W, H], color_by="intensity", colormap="turbo", point_size=2.0, gpu_timestamps=False,
                       backend="cpu", raster="compute")
    rows = []
    os.environ["POINTFLOW_CPU_RASTER_ADAPTIVE"] = "0"  # the thread count this bench sets, every frame
    for n in sizes:
        world, inten = tiled(base, inten0, n)
        f = make_frame(world, inten)
        cam = camera_for(world)
        del world
        rs = {}
        for sp in splits:
            os.environ["POINTFLOW_CPU_RASTER_SPLIT"] = sp
            rs[sp] = CpuComputeRenderer(replace(cfg), n, ["intensity"])
        del os.environ["POINTFLOW_CPU_RASTER_SPLIT"]
        pairs = [(sp, t) for sp in splits for t in threads]
        wall: dict[tuple[str, int], list[float]] = {p: [] for p in pairs}
        cpu: dict[tuple[str, int], list[float]] = {p: [] for p in pairs}
        used: dict[tuple[str, int], set] = {p: set() for p in pairs}
        step, head = max(n // 100, 1), 0
        for p in pairs:  # warm-up
            numba.set_num_threads(p[1])
            f.dirty = None
            rs[p[0]].render(f, cam)
        for i in range(rounds):
            for sp, t in pairs[i % len(pairs):] + pairs[:i % len(pairs)]:
                a, b = head, min(head + step, n)
                head = b % n
                f.dirty = [(a, b)]
                numba.set_num_threads(t)
                t0, c0 = time.perf_counter(), time.process_time()
                st = rs[sp].render(f, cam)
                rs[sp].read_image()
                wall[(sp, t)].append((time.perf_counter() - t0) * 1e3)
                cpu[(sp, t)].append((time.process_time() - c0) * 1e3)
                used[(sp, t)].add(st.extra["split"])
        numba.set_num_threads(most)
        imgs = {sp: r.read_image().tobytes() for sp, r in rs.items()}
        row: dict[str, Any] = {"points": n, "rounds": rounds, "threads": threads, "same_image": len(set(imgs.values())) == 1,
                               "load_after": [round(x, 2) for x in os.getloadavg()], "splits": {}}
        for sp in splits:
            one = np.asarray(wall[(sp, 1)])
            d: dict[str, Any] = {}
            for t in threads:
                w = np.asarray(wall[(sp, t)])
                d[str(t)] = {"wall_ms": float(np.median(w)), "cpu_ms": float(np.median(cpu[(sp, t)])),
                             "speedup_per_round_median": float(np.median(one / w)),
                             "drawn_with": sorted(used[(sp, t)]), "all_wall_ms": w.round(3).tolist(),
                             "all_cpu_ms": np.round(cpu[(sp, t)], 3).tolist()}
            row["splits"][sp] = d
            print(f"  {n:>9,} {sp:6s} " + "  ".join(
                f"{t}T {d[str(t)]['wall_ms']:6.1f} ms (x{d[str(t)]['speedup_per_round_median']:.2f})" for t in threads),
                flush=True)
        rows.append(row)
        del f, rs
    return {"scene": scene, "size": [W, H], "numba": numba.__version__,
            "threading_layer": _layer(), "rows": rows, "machine": _harness.machine_done(machine),
            "measured_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "command": _harness.command()}


def _layer() -> Optional[str]:
    import numba
    try:
        return numba.threading_layer()
    except ValueError:  # no parallel region has run
        return None


def chart(res: dict[str, Any], path: Path) -> None:
    """Frame time against threads, one panel per size, one line per split."""
    if (plt := _harness.pyplot()) is None:
        return
    rows = res["rows"]
    fig, axes = plt.subplots(1, len(rows), figsize=(4.2 * len(rows), 3.8), squeeze=False)
    for ax, row in zip(axes[0], rows):
        for sp, d in row["splits"].items():
            ts = [int(t) for t in d]
            ax.plot(ts, [d[str(t)]["wall_ms"] for t in ts], "o-", label=sp)
            for t in ts[1:]:
                ax.annotate(f"x{d[str(t)]['speedup_per_round_median']:.2f}", (t, d[str(t)]["wall_ms"]),
                            xytext=(4, 4), textcoords="offset points", fontsize=7)
        ax.set_title(f"{row['points']:,} points", fontsize=9)
        ax.set_xlabel("numba threads")
        ax.set_ylabel("median frame ms (interleaved)")
        ax.set_ylim(bottom=0)
        ax.set_xticks(row["threads"])
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"compiled cpu raster, {res['size'][0]}x{res['size'][1]}, 2 px; "
                 f"{_harness.machine_line(res['machine'])}", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="*", default=[100_000, 1_000_000])
    ap.add_argument("--rounds", type=int, default=15, help="frames per (split, threads) pair, interleaved")
    ap.add_argument("--splits", default=",".join(SPLITS))
    ap.add_argument("--out", default=str(_harness.RESULTS / "cpu_threads.json"))
    a = ap.parse_args(argv)
    res = measure(a.sizes, a.rounds, tuple(a.splits.split(",")))
    path = _harness.write_result(a.out, res)
    chart(res, path.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
