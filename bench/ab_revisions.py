"""A/B of two git revisions in one run: the ingest, render, pipeline and views benchmarks (each
revision's own ``bench/`` script against its own ``pointflow``), interleaved round by round
(ABBA), so a refactor can be shown to stay within the run-to-run spread:

    .venv/bin/python bench/ab_revisions.py --base c138342 --head main ingest render pipeline
    .venv/bin/python bench/ab_revisions.py --base main --head . --quick ingest     # this work tree as head

Each revision is checked out with ``git archive`` into a private folder (``.`` means this
checkout as it is, uncommitted changes included). Per benchmark and figure it writes both
sides' samples, medians, spreads (min..max) and head/base, and whether the head's median lies
within the run-to-run spread (the larger of the two sides' max - min) of the base's, into
``bench/results/ab_revisions.json`` (``--out``), with the machine description and the load
before and after: the machine is shared, so read the figures with the load.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any, Callable

import _harness as H


def _ingest(res: dict) -> dict[str, float]:
    out = {}
    for r in res["rows"]:
        n = r["chunk_points"]
        out[f"of_raw@{n}"] = r["of_raw"]
        out[f"ingest_Mpts_s@{n}"] = r["pointflow_pts_s"] / 1e6
        out[f"ingest_Mpts_per_cpu_s@{n}"] = r["ingest_pts_per_cpu_s"] / 1e6
    return out


def _render(res: dict) -> dict[str, float]:
    out = {}
    for r in res["rows"]:
        for m in ("quads", "compute"):
            if f"{m}_ms" in r:
                out[f"{m}_ms@{r['points']}"] = r[f"{m}_ms"]
    return out


def _pipeline(res: dict) -> dict[str, float]:
    return {f"fps_{m}": v for m, v in res["median_fps"].items()}


#: name -> (script, full-size arguments, --quick arguments, figures from its JSON, lower is better)
def _views(res: dict) -> dict[str, float]:
    ov, dr, fv = res["one_view"], res["drag"], res["four_views"]
    return {"view_client_fps": ov["client_fps_median"], "view_over_render_alone": ov["ratio"],
            "drag_p50_ms": dr["p50_ms"], "four_views_over_one": fv["ratio"]}


BENCHES: dict[str, tuple[str, list[str], list[str], Callable[[dict], dict[str, float]], bool]] = {
    "ingest": ("bench_ingest.py", ["--points", "10000000", "--repeats", "3", "--sizes", "1000,10000", "--no-replay",
                                   "--no-frames"],
               ["--points", "300000", "--repeats", "1", "--sizes", "10000", "--no-replay", "--no-frames"], _ingest, False),
    "render": ("bench_render.py", ["--sizes", "100000", "1000000", "--cpu-max", "0"],
               ["--sizes", "100000", "--cpu-max", "0", "--quick"], _render, True),
    "pipeline": ("bench_pipeline.py", ["--seconds", "8", "--rounds", "1"],
                 ["--seconds", "3", "--warmup", "4", "--rounds", "1"], _pipeline, False),
    # a view's frames/s through the view server, drag to frame (higher is better but for drag_p50_ms)
    "views": ("bench_views.py", ["--points", "300000"], ["--points", "50000", "--quick"], _views, False),
}


def compare(base: list[float], head: list[float], lower_better: bool) -> dict[str, Any]:
    """Both sides' spreads, head/base of the medians, and whether the difference of the
    medians is within the run-to-run spread."""
    b, h = H.spread(base), H.spread(head)
    run_to_run = max(b["max"] - b["min"], h["max"] - h["min"])
    return {"base": base, "head": head, "base_spread": b, "head_spread": h,
            "head_over_base": h["median"] / b["median"] if b["median"] else None,
            "run_to_run_spread": run_to_run, "lower_is_better": lower_better,
            # one round has no spread to judge by
            "within_spread": abs(h["median"] - b["median"]) <= run_to_run if min(b["n"], h["n"]) > 1 else None}


def run_bench(name: str, root: Path, quick: bool, log: Path) -> dict[str, float]:
    script, full, small, figures, _ = BENCHES[name]
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "out.json")
        with open(log, "a") as f:
            p = subprocess.run([sys.executable, str(root / "bench" / script), *(small if quick else full), "--out", out],
                               cwd=root, env=H.checkout_env(root), stdout=f, stderr=subprocess.STDOUT)
        if p.returncode:
            raise SystemExit(f"{name} failed in {root} (exit {p.returncode}); its output is in {log}")
        return figures(json.loads(Path(out).read_text()))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("benches", nargs="+", choices=sorted(BENCHES), help="which benchmarks")
    ap.add_argument("--base", required=True, help="the baseline revision (a commit, branch or tag)")
    ap.add_argument("--head", default=".", help="the revision compared with it ('.': this checkout, the default)")
    ap.add_argument("--rounds", type=int, default=3, help="ABBA rounds (each runs every benchmark on both sides)")
    ap.add_argument("--quick", action="store_true", help="small sizes: proves the set-up, not the figures")
    ap.add_argument("--out", default=str(H.RESULTS / "ab_revisions.json"))
    a = ap.parse_args(argv)
    machine = H.machine()
    log = Path(a.out).with_suffix(".log")
    log.parent.mkdir(parents=True, exist_ok=True)
    log.write_text("")
    with H.checkout_or_revision(a.base) as (base_root, base_sha), \
            H.checkout_or_revision(a.head) as (head_root, head_sha):
        roots = {"base": base_root, "head": head_root}
        samples: dict[str, dict[str, dict[str, list[float]]]] = {b: {"base": {}, "head": {}} for b in a.benches}

        def one(side: str) -> dict[str, dict[str, float]]:
            return {b: run_bench(b, roots[side], a.quick, log) for b in a.benches}

        def show(i: int, side: str, figs: dict[str, dict[str, float]]) -> None:
            for b, fig in figs.items():
                for k, v in fig.items():
                    samples[b][side].setdefault(k, []).append(v)
            print(f"round {i + 1} {side}: " + "; ".join(f"{b} " + ", ".join(f"{k} {v:.3g}" for k, v in fig.items())
                                                      for b, fig in figs.items()) + f"  (load {os.getloadavg()[0]:.1f})",
                  flush=True)

        H.interleave({"base": lambda: one("base"), "head": lambda: one("head")}, a.rounds, show)
    res: dict[str, Any] = {"base": {"rev": a.base, "commit": base_sha}, "head": {"rev": a.head, "commit": head_sha},
                           "rounds": a.rounds, "quick": a.quick, "command": H.command(), "benches": {}}
    for b in a.benches:
        lower = BENCHES[b][4]
        res["benches"][b] = {k: compare(v, samples[b]["head"][k], lower) for k, v in samples[b]["base"].items()}
    res["machine"] = H.machine_done(machine)
    print(f"\n{'figure':<34}{'base median':>12}{'head median':>12}{'head/base':>10}  within spread")
    for b, figs in res["benches"].items():
        for k, c in figs.items():
            print(f"{b + ' ' + k:<34}{c['base_spread']['median']:>12.4g}{c['head_spread']['median']:>12.4g}"
                  f"{c['head_over_base'] or float('nan'):>10.3f}  "
                  f"{ {True: 'yes', False: 'NO', None: 'n/a (one round)'}[c['within_spread']]}"
                  f" (spread {c['run_to_run_spread']:.3g})")
    print(f"load: {res['machine']['uptime_before']} -> {res['machine']['uptime_after']}")
    H.write_result(a.out, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
