"""The compiled cpu raster against its thread count (issue 41): frame time at 1..N numba
threads for each way of sharing the work (``auto``, ``bins``, ``points``; the env
``POINTFLOW_CPU_RASTER_SPLIT`` of :mod:`pointflow.render.cpu_compute`), frames interleaved in
rotating order so that every (split, threads) pair sees the same load; the scene of
``bench_render.py --cpu-raster`` (the autzen tile repeated to N points, 1280x720, 2 px
squares, turbo by intensity, 1% of the ring rewritten per frame, output = read_image):

    PYTHONPATH=$PWD .venv/bin/python bench/bench_cpu_threads.py --sizes 100000 1000000
    NUMBA_NUM_THREADS=4 PYTHONPATH=$PWD .venv/bin/python bench/bench_cpu_threads.py   # up to 4 threads
    PYTHONPATH=$PWD .venv/bin/python bench/bench_cpu_threads.py --by-split   # one renderer's data warm

Every pair interleaved (the default), each frame reads its renderer's ring copy and buffers back
from memory (three renderers of 1M points do not fit the last-level cache); ``--by-split`` runs
one split after the other, interleaving only the thread counts, as a render stage (one renderer)
draws. ``--block K``: K consecutive frames per turn (their median is the turn's figure): a render
stage keeps its thread count from frame to frame, and a second core left idle for a frame at one
thread is slower to start the next frame's work than one that drew the frame before:

    PYTHONPATH=$PWD .venv/bin/python bench/bench_cpu_threads.py --by-split --block 10 --rounds 9

``--cull N`` instead: batch culling (issue 41) on a ring of N points, the whole ring in view
against a view of about a tenth of it (the same ring, the camera fitted to a corner block of
the tiles), each with culling on and off (``POINTFLOW_CPU_RASTER_CULL``), interleaved; writes
``bench/results/cpu_cull.json``:

    PYTHONPATH=$PWD .venv/bin/python bench/bench_cpu_threads.py --cull 4000000
    PYTHONPATH=$PWD .venv/bin/python bench/bench_cpu_threads.py --cull 4000000 --tiers gl   # gl_cull.json
    PYTHONPATH=$PWD .venv/bin/python bench/bench_cpu_threads.py --cull 4000000 --tiers cpu  # numpy_cull.json

``--cull N --tiers wgpu-compute,wgpu-quads``: the same for the wgpu tier's raster methods
(frame = render + read_image, which waits for the GPU); writes ``bench/results/wgpu_cull.json``
(one entry per tier under ``tiers``):

    PYTHONPATH=$PWD .venv/bin/python bench/bench_cpu_threads.py --cull 4000000 --tiers wgpu-compute,wgpu-quads

N is numba's thread count (``NUMBA_NUM_THREADS``, default the cores). Per pair: the median wall
time and process CPU time per frame; per split the speed-up at t threads = the median of the
per-round ratios (1-thread frame / t-thread frame of the same round), so load that changes
between rounds cancels. Beside it, what the machine itself gave t threads in the same round
(``_harness/machine_ceiling.py``: a compute-bound and a streaming loop of about a frame's
length, timed after each round's frames): ``machine_speedup_compute`` / ``_stream``, and
``speedup_over_machine_compute``, the median of the per-round raster speed-up over the
compute loop's (1.0: the raster gains what the cores give). Writes ``bench/results/cpu_threads.json`` and the chart ``.png``.
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
from _harness.machine_ceiling import Ceiling
from _harness.scenes import H, W, base_cloud, camera_for, make_frame, tiled
from pointflow.config import RenderConfig

SPLITS = ("auto", "bins", "points")


def measure(sizes: list[int], rounds: int, splits: tuple[str, ...], by_split: bool = False,
            block: int = 1) -> dict[str, Any]:
    import numba

    from pointflow.render.cpu_compute import CpuComputeRenderer
    machine = _harness.machine()
    most = int(numba.config.NUMBA_NUM_THREADS)
    threads = list(range(1, most + 1))
    base, inten0, scene = base_cloud()
    cfg = RenderConfig(size=[W, H], color_by="intensity", colormap="turbo", point_size=2.0, gpu_timestamps=False,
                       backend="cpu", raster="compute")
    rows = []
    ceiling = Ceiling()
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
        # the machine's own gain in each turn's round: {loop: {(split, t): [1-thread ms / t-thread ms]}}
        gain: dict[str, dict[tuple[str, int], list[float]]] = {"compute": {p: [] for p in pairs},
                                                                "stream": {p: [] for p in pairs}}
        step, head = max(n // 100, 1), 0
        for p in pairs:  # warm-up
            numba.set_num_threads(p[1])
            f.dirty = None
            rs[p[0]].render(f, cam)
        if by_split:  # one split after the other, its thread counts interleaved (one renderer's data warm)
            order = [[(sp, t) for t in (threads[i % len(threads):] + threads[:i % len(threads)])]
                     for sp in splits for i in range(rounds)]
        else:
            order = [pairs[i % len(pairs):] + pairs[:i % len(pairs)] for i in range(rounds)]
        for batch in order:
            for sp, t in batch:
                numba.set_num_threads(t)
                ws, cs = [], []
                for _ in range(block):  # consecutive frames at one thread count (a block's median counts)
                    a, b = head, min(head + step, n)
                    head = b % n
                    f.dirty = [(a, b)]
                    t0, c0 = time.perf_counter(), time.process_time()
                    st = rs[sp].render(f, cam)
                    rs[sp].read_image()
                    ws.append((time.perf_counter() - t0) * 1e3)
                    cs.append((time.process_time() - c0) * 1e3)
                    used[(sp, t)].add(st.extra["split"])
                wall[(sp, t)].append(float(np.median(ws)))
                cpu[(sp, t)].append(float(np.median(cs)))
            ceil = {}
            for t in sorted({t for _, t in batch}):  # the same round: what the machine gave t threads
                numba.set_num_threads(t)
                ceil[t] = ceiling.time()
            for sp, t in batch:
                for loop in gain:
                    gain[loop][(sp, t)].append(ceil[1][loop] / ceil[t][loop])
        numba.set_num_threads(most)
        imgs = {sp: r.read_image().tobytes() for sp, r in rs.items()}
        row: dict[str, Any] = {"points": n, "rounds": rounds, "threads": threads, "same_image": len(set(imgs.values())) == 1,
                               "interleaved": "threads within a split" if by_split else "every (split, threads) pair",
                               "frames_per_block": block,
                               "load_after": [round(x, 2) for x in os.getloadavg()], "splits": {}}
        for sp in splits:
            one = np.asarray(wall[(sp, 1)])
            d: dict[str, Any] = {}
            for t in threads:
                w = np.asarray(wall[(sp, t)])
                d[str(t)] = {"wall_ms": float(np.median(w)), "cpu_ms": float(np.median(cpu[(sp, t)])),
                             "speedup_per_round_median": float(np.median(one / w)),
                             "machine_speedup_compute": float(np.median(gain["compute"][(sp, t)])),
                             "machine_speedup_stream": float(np.median(gain["stream"][(sp, t)])),
                             "speedup_over_machine_compute": float(np.median(one / w / gain["compute"][(sp, t)])),
                             "drawn_with": sorted(used[(sp, t)]), "all_wall_ms": w.round(3).tolist(),
                             "all_cpu_ms": np.round(cpu[(sp, t)], 3).tolist()}
            row["splits"][sp] = d
            print(f"  {n:>9,} {sp:6s} " + "  ".join(
                f"{t}T {d[str(t)]['wall_ms']:6.1f} ms (x{d[str(t)]['speedup_per_round_median']:.2f}; machine "
                f"x{d[str(t)]['machine_speedup_compute']:.2f} compute, x{d[str(t)]['machine_speedup_stream']:.2f} "
                f"stream)" for t in threads), flush=True)
        rows.append(row)
        del f, rs
    return {"scene": scene, "size": [W, H], "numba": numba.__version__,
            "threading_layer": _layer(), "rows": rows, "machine": _harness.machine_done(machine),
            "measured_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "command": _harness.command()}


#: ``--tiers``: the compiled cpu raster, the wgpu tier's two methods, the gl tier and the numpy
#: reference (``cpu``), each culling whole batches (render/batches.py)
CULL_TIERS = ("cpu-compute", "wgpu-compute", "wgpu-quads", "gl", "cpu")


def cull(n: int, rounds: int, tiers: tuple[str, ...] = ("cpu-compute",)) -> dict[str, Any]:
    """Frame time of the whole ring in view and of a view of ~10% of it, culling on and off,
    for each tier (the compiled cpu raster alone: its result; otherwise ``{"tiers": ...}``)."""
    from pointflow.render.camera import Camera
    for t in tiers:
        if t not in CULL_TIERS:
            raise SystemExit(f"--tiers: unknown tier {t!r} (expected some of {', '.join(CULL_TIERS)})")
    base, inten0, scene = base_cloud()
    world, inten = tiled(base, inten0, n)
    f = make_frame(world, inten)
    lo, hi = world.min(0), world.max(0)
    cams = {"whole": camera_for(world)}
    # looking straight down from the height at which the view covers a twentieth of the ground
    # (about a tenth of the points: the corner tiles are denser than the mean),
    # centred on a point that keeps the whole view over the data
    t, asp = np.tan(np.radians(60.0) / 2), W / H
    h = np.sqrt(0.05 * (hi[0] - lo[0]) * (hi[1] - lo[1]) / (4 * asp * t * t))
    c = np.array([lo[0] + 1.2 * asp * t * h, lo[1] + 1.2 * t * h, hi[2]])
    cams["tenth"] = Camera(eye=c + [0, -1e-3 * h, h], target=c - [0, 0, h], up=[0, 1, 0], fov_deg=60.0,
                           near=0.01 * h, far=4 * h)
    del world
    if len(tiers) == 1 and not tiers[0].startswith("wgpu"):
        return _cull_tier(f, cams, n, rounds, tiers[0], scene)
    out = {"points": n, "scene": scene, "tiers": {}}
    for t in tiers:
        out["tiers"][t] = _cull_tier(f, cams, n, rounds, t, scene)
    return out


def _make_cull(tier: str, n: int, on: str) -> Any:
    """The tier's renderer with culling ``on`` ("1") or off ("0")."""
    cfg = RenderConfig(size=[W, H], color_by="intensity", colormap="turbo", point_size=2.0, gpu_timestamps=False,
                       backend="cpu", raster="compute")
    os.environ["POINTFLOW_CPU_RASTER_CULL"] = on
    try:
        if tier == "cpu-compute":
            from pointflow.render.cpu_compute import CpuComputeRenderer
            return CpuComputeRenderer(cfg, n, ["intensity"])
        if tier == "cpu":
            from pointflow.render.cpu import CpuRenderer
            return CpuRenderer(replace(cfg, raster="auto"), n, ["intensity"])
        if tier == "gl":
            from pointflow.render.gl import GlRenderer
            return GlRenderer(replace(cfg, backend="gl", raster="auto"), n, ["intensity"])
        from pointflow.render.wgpu_tier import WgpuRenderer
        return WgpuRenderer(replace(cfg, backend="wgpu", raster=tier[5:]), n, ["intensity"])
    finally:
        del os.environ["POINTFLOW_CPU_RASTER_CULL"]


def _cull_tier(f: Any, cams: dict[str, Any], n: int, rounds: int, tier: str, scene: str) -> dict[str, Any]:
    import numba
    machine = _harness.machine()
    os.environ["POINTFLOW_CPU_RASTER_ADAPTIVE"] = "0"
    os.environ["POINTFLOW_CPU_RASTER_SPLIT"] = "bins"
    rs = {on: _make_cull(tier, n, on) for on in ("1", "0")}
    del os.environ["POINTFLOW_CPU_RASTER_SPLIT"]
    pairs = [(v, on) for v in cams for on in rs]
    wall: dict[tuple[str, str], list[float]] = {p: [] for p in pairs}
    cpu: dict[tuple[str, str], list[float]] = {p: [] for p in pairs}
    seen: dict[str, float] = {}
    culled: dict[tuple[str, str], int] = {}
    imgs: dict[tuple[str, str], bytes] = {}
    step, head = max(n // 100, 1), 0
    for v, on in pairs:
        f.dirty = None
        st = rs[on].render(f, cams[v])
        rs[on].read_image()  # (the wgpu tier fills drawn once the GPU is done)
        seen[v] = st.drawn / n
    for i in range(rounds):
        for v, on in pairs[i % len(pairs):] + pairs[:i % len(pairs)]:
            a, b = head, min(head + step, n)
            head = b % n
            f.dirty = [(a, b)]
            t0, c0 = time.perf_counter(), time.process_time()
            st = rs[on].render(f, cams[v])
            imgs[(v, on)] = rs[on].read_image().tobytes()
            wall[(v, on)].append((time.perf_counter() - t0) * 1e3)
            cpu[(v, on)].append((time.process_time() - c0) * 1e3)
            culled[(v, on)] = st.extra["culled_points"]
    med = {f"{v}/cull_{'on' if on == '1' else 'off'}": float(np.median(wall[(v, on)])) for v, on in pairs}
    # process CPU time (every thread's work): less sensitive than wall time to waiting for a core
    med_cpu = {f"{v}/cull_{'on' if on == '1' else 'off'}": float(np.median(cpu[(v, on)])) for v, on in pairs}
    info = rs["1"].info() if tier != "cpu-compute" else {}
    for r in rs.values():
        r.close()
    res = {"tier": tier, "points": n, "rounds": rounds, "scene": scene,
           "threads": int(numba.get_num_threads()) if tier == "cpu-compute" else None,
           "adapter": info.get("adapter"), "chunks": info.get("chunks"),
           "fraction_in_view": seen, "median_ms": med,
           "tenth_over_whole_cull_on": med["tenth/cull_on"] / med["whole/cull_on"],
           "tenth_over_whole_cull_off": med["tenth/cull_off"] / med["whole/cull_off"],
           "median_cpu_ms": med_cpu,
           "cpu_tenth_over_whole_cull_on": med_cpu["tenth/cull_on"] / med_cpu["whole/cull_on"],
           "cpu_tenth_over_whole_cull_off": med_cpu["tenth/cull_off"] / med_cpu["whole/cull_off"],
           "culled_points": {f"{v}/{on}": c for (v, on), c in culled.items()},
           "same_image_cull_on_off": all(imgs[(v, "1")] == imgs[(v, "0")] for v in cams),
           "all_ms": {f"{v}/{on}": w for (v, on), w in wall.items()},
           "machine": _harness.machine_done(machine), "command": _harness.command(),
           "measured_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    print(f"  {tier}: {n:,} points; in view: whole {seen['whole']:.1%}, tenth {seen['tenth']:.1%}; " +
          "  ".join(f"{k} {v:.1f} ms" for k, v in med.items()) +
          f"; tenth/whole: cull on {res['tenth_over_whole_cull_on']:.3f}, off {res['tenth_over_whole_cull_off']:.3f}"
          f" (CPU time: on {res['cpu_tenth_over_whole_cull_on']:.3f}, off {res['cpu_tenth_over_whole_cull_off']:.3f});"
          f" same image on/off: {res['same_image_cull_on_off']}", flush=True)
    return res


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
                mach = d[str(t)].get("machine_speedup_compute")  # (results before wave 5g lack it)
                ax.annotate(f"x{d[str(t)]['speedup_per_round_median']:.2f}" + (f" (machine x{mach:.2f})" if mach else ""),
                            (t, d[str(t)]["wall_ms"]), xytext=(4, 4), textcoords="offset points", fontsize=7)
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
    ap.add_argument("--by-split", action="store_true",
                    help="one split after the other, only its thread counts interleaved: the data of one renderer "
                         "stays in the caches, as in a render stage (default: every pair interleaved, each frame "
                         "reading its renderer's data back from memory)")
    ap.add_argument("--out", default=None, help="default bench/results/cpu_threads.json (cpu_cull.json with --cull)")
    ap.add_argument("--cull", type=int, default=0, metavar="N", help="batch culling on a ring of N points instead")
    ap.add_argument("--tiers", default="cpu-compute",
                    help=f"with --cull: some of {','.join(CULL_TIERS)} (any wgpu one: wgpu_cull.json)")
    ap.add_argument("--block", type=int, default=1,
                    help="consecutive frames per (split, threads) turn; its median is the round's figure (default 1: "
                         "the thread count changes every frame, as a render stage never does; its adaptive choice "
                         "keeps one count and re-tries the other every 30 frames)")
    a = ap.parse_args(argv)
    if a.cull:
        tiers = tuple(t.strip() for t in a.tiers.split(",") if t.strip())
        names = {("cpu-compute",): "cpu_cull.json", ("gl",): "gl_cull.json", ("cpu",): "numpy_cull.json"}
        name = names.get(tiers, "wgpu_cull.json")
        _harness.write_result(a.out or _harness.RESULTS / name, cull(a.cull, a.rounds, tiers))
        return 0
    a.out = a.out or str(_harness.RESULTS / "cpu_threads.json")
    res = measure(a.sizes, a.rounds, tuple(a.splits.split(",")), a.by_split, max(1, a.block))
    path = _harness.write_result(a.out, res)
    chart(res, path.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
