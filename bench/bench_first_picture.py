"""First picture on an empty numba cache (issue 36): the demo run from the command line,
timed from the command's start to its first PNG, and the frames it draws in its run.

    XDG_RUNTIME_DIR=/tmp/xdg .venv/bin/python bench/bench_first_picture.py [--busy 2] [--rounds 1]

Per round, each case is one ``pointflow run configs/demo.yaml --duration 10 --out DIR``,
the cases alternated:

* ``warm``: a numba cache filled ahead (``pointflow warm``): the compiled raster from the
  first frame; the same-run baseline.
* ``empty:<tiers>``: a fresh ``NUMBA_CACHE_DIR``: the render stage draws with the tier it
  takes meanwhile (``POINTFLOW_RASTER_MEANWHILE=<tiers>``, one case per ``--meanwhile``
  value) and compiles in the background; frames also as a ratio to ``warm``'s;
* ``second``: the next run on the first empty case's cache once its compiler has finished
  (started with the compiled raster: no ``raster_switched_after_s`` in its stats.json).

``--busy N`` runs N busy loops (``while True: pass`` processes) for the whole measurement.
Writes bench/results/first_picture.json.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

import _harness as H

ROOT = H.ROOT


def _busy(n: int) -> list[subprocess.Popen]:
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def _wait_compiler(cache: str, limit_s: float = 600.0) -> float:
    """Seconds until no compiler holds a lock under ``cache``."""
    from pointflow import jitcache

    t0 = time.monotonic()
    while time.monotonic() - t0 < limit_s:
        dirs = [os.path.dirname(p) for p in glob.glob(os.path.join(cache, "*", jitcache.LOCK_NAME))]
        if dirs and not any(jitcache.compiling(d) for d in dirs):
            break
        time.sleep(0.5)
    return time.monotonic() - t0


def one_run(cache: str, seconds: int, meanwhile: str | None) -> dict:
    out = tempfile.mkdtemp(prefix="pf-first-")
    env = dict(os.environ, NUMBA_CACHE_DIR=cache)
    if meanwhile:
        env["POINTFLOW_RASTER_MEANWHILE"] = meanwhile
    t0 = time.monotonic()
    p = subprocess.Popen([sys.executable, "-m", "pointflow.cli", "run", str(ROOT / "configs" / "demo.yaml"),
                          "--duration", str(seconds), "--out", out], env=env, cwd=ROOT,
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    first = None
    while p.poll() is None:
        if first is None and glob.glob(os.path.join(out, "frame_*.png")):
            first = time.monotonic() - t0
        time.sleep(0.05)
    wall = time.monotonic() - t0
    err = p.stderr.read() if p.stderr else ""
    try:
        with open(os.path.join(out, "stats.json")) as f:
            r = json.load(f)["stages"]["render"]
    except (OSError, ValueError, KeyError) as exc:
        shutil.rmtree(out, ignore_errors=True)
        raise SystemExit(f"run failed ({exc}): {err.strip().splitlines()[-1:] }")
    if first is None and r.get("pngs"):
        first = wall  # written after the last poll
    shutil.rmtree(out, ignore_errors=True)
    return {"first_png_s": None if first is None else round(first, 2), "frames": int(r.get("frames", 0)),
            "raster_at_end": r.get("raster"), "tier_at_end": r.get("tier"), "meanwhile": r.get("raster_meanwhile"),
            "switched_after_s": r.get("raster_switched_after_s"), "wall_s": round(wall, 2), "rc": p.returncode}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--busy", type=int, default=0, help="busy loops beside the runs")
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--seconds", type=int, default=10, help="--duration of each run")
    ap.add_argument("--meanwhile", nargs="+", default=["default"],
                    help="one empty-cache case per value: the tiers drawing while compiling (e.g. wgpu,gl,cpu or "
                         "cpu; default: the shipped order); the first one is also run a second time")
    ap.add_argument("--out", default=str(H.RESULTS / "first_picture.json"))
    a = ap.parse_args()
    mach = H.machine(busy_loops=a.busy)
    warm_cache = tempfile.mkdtemp(prefix="pf-numba-warm-")
    subprocess.run([sys.executable, "-m", "pointflow.cli", "warm"], env=dict(os.environ, NUMBA_CACHE_DIR=warm_cache),
                   cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
    busy = _busy(a.busy)
    cases = ["warm"] + [f"empty:{m}" for m in a.meanwhile]
    rounds = []
    try:
        for i in range(a.rounds):
            rnd: dict = {}
            for case in H.order(cases, i):
                m = case.partition(":")[2]
                mw = None if m in ("", "default") else m
                if case == "warm":
                    rnd[case] = one_run(warm_cache, a.seconds, None)
                else:
                    cache = tempfile.mkdtemp(prefix="pf-numba-empty-")
                    rnd[case] = one_run(cache, a.seconds, mw)
                    rnd[case]["compiler_done_after_run_s"] = round(_wait_compiler(cache), 1)
                    if case == cases[1]:
                        rnd["second"] = one_run(cache, a.seconds, mw)
                    shutil.rmtree(cache, ignore_errors=True)
                print(f"round {i} {case}: {rnd[case]}", flush=True)
            for case in cases[1:]:
                rnd[case]["frames_ratio_to_warm"] = round(rnd[case]["frames"] / max(rnd["warm"]["frames"], 1), 3)
            print(f"round {i} second: {rnd['second']}  ({H.uptime()})", flush=True)
            rounds.append(rnd)
    finally:
        for b in busy:
            b.kill()
            b.wait()
        shutil.rmtree(warm_cache, ignore_errors=True)

    def med(case: str, k: str):
        v = [r[case][k] for r in rounds if r[case].get(k) is not None]
        return statistics.median(v) if v else None

    summary = {c: {k: med(c, k) for k in ("first_png_s", "frames", "frames_ratio_to_warm")} for c in cases + ["second"]}
    summary["second_started_compiled"] = all(r["second"]["switched_after_s"] is None
                                             and r["second"]["raster_at_end"] == "compiled" for r in rounds)
    res = {"command": H.command(), "machine": H.machine_done(mach), "busy_loops": a.busy, "seconds": a.seconds,
           "cases": cases, "rounds": rounds, "summary": summary}
    path = H.write_result(a.out, res)
    print(json.dumps(summary), "->", path)


if __name__ == "__main__":
    main()
