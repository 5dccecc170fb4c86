"""A/B of the wgpu tier's frame time between two checkouts (for refactors of the render stage):
each checkout in its own long-lived worker process with both raster methods set up on the same
scene as ``bench_render.py`` (Autzen tile when present, 1280x720, 2 px squares, turbo by
intensity, 1% of the ring rewritten per frame, output = read_image), the driver alternating
A and B batch by batch (ABBA), medians of all frames and of the per-batch ratios B/A:

    git archive main pointflow | tar -x -C /tmp/base
    .venv/bin/python bench/ab_raster.py /tmp/base . --sizes 100000 1000000 --rounds 8

Writes the result JSON (``--out``) when asked; prints the medians and ratios.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from typing import Any

import _harness as H

METHODS = ("quads", "compute")


def worker() -> None:
    """Answers setup/run/quit lines for the checkout this process imports (``PYTHONPATH``)."""
    from dataclasses import replace

    import pointflow
    from _harness import scenes as B
    from pointflow.config import RenderConfig
    from pointflow.render.wgpu_tier import WgpuRenderer, select_adapter
    adapter, _ = select_adapter()
    cfg = RenderConfig(size=[B.W, B.H], color_by="intensity", colormap="turbo", point_size=2.0,
                       gpu_timestamps=False)
    base, inten0, _scene = B.base_cloud()
    state: dict[str, Any] = {}
    for line in sys.stdin:
        cmd = line.split()
        if cmd[0] == "setup":
            for r in state.get("rs", {}).values():
                r.close()
            n = int(cmd[1])
            world, inten = B.tiled(base, inten0, n)
            f = B.make_frame(world, inten)
            cam = B.camera_for(world)
            rs = {m: WgpuRenderer(replace(cfg, raster=m), n, ["intensity"], adapter=adapter) for m in METHODS}
            for r in rs.values():
                r.render(f, cam)
                r.read_image()
            state = {"rs": rs, "f": f, "cam": cam, "n": n, "head": 0}
            print(json.dumps({"ok": pointflow.__file__}), flush=True)
        elif cmd[0] == "run":
            m, k = cmd[1], int(cmd[2])
            f, cam, n, r = state["f"], state["cam"], state["n"], state["rs"][m]
            ts = []
            for _ in range(k):
                a = state["head"]
                b = min(a + max(n // 100, 1), n)
                state["head"] = b % n
                f.dirty = [(a, b)]
                t0, c0 = time.perf_counter(), time.process_time()
                r.render(f, cam)
                r.read_image()
                ts.append([(time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3])
            print(json.dumps(ts), flush=True)
        elif cmd[0] == "quit":
            break
    for r in state.get("rs", {}).values():
        r.close()


def main(argv=None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if args[:1] == ["--worker"]:
        worker()
        return 0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a", help="checkout A (the baseline), a directory holding pointflow/")
    ap.add_argument("b", help="checkout B")
    ap.add_argument("--sizes", type=int, nargs="*", default=[100_000, 1_000_000])
    ap.add_argument("--rounds", type=int, default=8, help="ABBA rounds per size and method")
    ap.add_argument("--frames", type=int, default=3, help="frames per batch")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    ws = {k: H.Worker([os.path.abspath(__file__), "--worker", root], root) for k, root in (("A", a.a), ("B", a.b))}
    machine = H.machine()
    rows = []
    try:
        for n in a.sizes:
            where = {k: w.ask(f"setup {n}")["ok"] for k, w in ws.items()}
            for m in METHODS:
                ts: dict[str, list[list[float]]] = {"A": [], "B": []}
                ratios: list[float] = []
                for i in range(a.rounds):
                    med = {}
                    for k in H.order("AB", i):
                        t = ws[k].ask(f"run {m} {a.frames}")
                        ts[k] += t
                        med[k] = statistics.median(x[0] for x in t)
                    ratios.append(med["B"] / med["A"])
                row: dict[str, Any] = {"points": n, "method": m, "frames_each": len(ts["A"]), "code": where,
                                       "median_batch_ratio": statistics.median(ratios)}
                # wall time, and the process's CPU time (lavapipe runs in the process's threads:
                # the work done, much less sensitive to other load on a shared machine)
                for j, what in ((0, "wall"), (1, "cpu")):
                    ma = statistics.median(x[j] for x in ts["A"])
                    mb = statistics.median(x[j] for x in ts["B"])
                    row.update({f"a_{what}_ms": ma, f"b_{what}_ms": mb, f"{what}_b_over_a": mb / ma,
                                f"a_all_{what}_ms": [x[j] for x in ts["A"]],
                                f"b_all_{what}_ms": [x[j] for x in ts["B"]]})
                rows.append(row)
                print(f"{n:>9,} {m:8s} wall: A {row['a_wall_ms']:8.1f} ms  B {row['b_wall_ms']:8.1f} ms  B/A "
                      f"{row['wall_b_over_a']:.3f} (median of batch ratios {row['median_batch_ratio']:.3f}); "
                      f"cpu: A {row['a_cpu_ms']:8.1f} ms  B {row['b_cpu_ms']:8.1f} ms  B/A {row['cpu_b_over_a']:.3f}",
                      flush=True)
    finally:
        for w in ws.values():
            w.close()
    if a.out:
        res = {"a": os.path.abspath(a.a), "b": os.path.abspath(a.b), "rows": rows, "machine": H.machine_done(machine),
               "measured_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "command": H.command()}
        H.write_result(a.out, res, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
