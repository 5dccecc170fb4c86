"""Start-up: how long from a command to its first picture, and where ``Pipeline.start()``
spends its time (issue 36, items 3 and 5). Every figure is one fresh process, timed from
just before it is spawned (CLOCK_MONOTONIC is shared by every process of the machine, so a
child reports "now - the parent's t0" at the instant it wrote its PNG):

* ``show``: ``pointflow.show(xyz, path=...)`` of 50,000 points, the whole call from a new
  Python (``import numpy, pointflow`` included) until the PNG is written;
* ``matplotlib``: a new Python saving matplotlib's 3D scatter of the same points to PNG
  (the baseline the issue names);
* ``rerun``: a new Python doing ``rr.init`` + ``rr.save`` + ``rr.log(Points3D)`` of the same
  points to an .rrd file (rerun-sdk, installed when missing as bench_api.py does);
* ``api``: ``Pipeline.from_dict`` with an ``api`` source, ``start()``, ``send`` of the same
  points, until the render stage drew them all, ``save_frame``: the shortest pipeline path;
* ``demo``: ``pointflow run configs/demo.yaml`` (a 1M-point ring, 100k-point scans), from
  the command until its first PNG exists in the output folder (then Ctrl-C);
* ``start``: ``Pipeline.start()`` of the demo (and with ``--record`` and ``--serve`` stages:
  6 stages), with each stage's ``startup_ms`` (interpreter, runtime, module, context,
  setup: pointflow/runtime/stagestate.py) for the chart by stage and cause.

``--base REV`` runs every measurement also against revision REV's pointflow (``git archive``
into a private folder, :func:`_harness.revision_tree`), interleaved round by round (ABBA):
before/after in one run. One warm-up round first (numba and Mesa caches filled: "warm").

    python bench/bench_startup.py --rounds 5 --base main
"""
from __future__ import annotations

import argparse
import contextlib
import os
import signal
import subprocess
import sys
import tempfile
import statistics
import time
from pathlib import Path
from typing import Any, Optional

import _harness as H

N_SHOW = 50_000

_CLOUD = "import numpy as np; xyz = np.random.default_rng(1).normal(size=({n}, 3)).astype(np.float32)"

SHOW = """import sys, time, json
t0 = float(sys.argv[1])
import contextlib
import numpy as np, pointflow
{cloud}
with contextlib.redirect_stdout(sys.stderr):  # show prints the PNG's path; stdout is the JSON
    pointflow.show(xyz, intensity=np.abs(xyz[:, 2]), path=sys.argv[2], size=(1280, 720))
print(json.dumps({{"png_s": time.monotonic() - t0}}))
"""

MATPLOTLIB = """import sys, time, json
t0 = float(sys.argv[1])
import numpy as np
import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt
{cloud}
fig = plt.figure(figsize=(12.8, 7.2), dpi=100)
ax = fig.add_subplot(projection="3d")
ax.scatter(xyz[:, 0], xyz[:, 1], xyz[:, 2], c=np.abs(xyz[:, 2]), s=1, cmap="turbo")
fig.savefig(sys.argv[2])
print(json.dumps({{"png_s": time.monotonic() - t0}}))
"""

RERUN = """import sys, time, json
t0 = float(sys.argv[1])
import numpy as np
import rerun as rr
{cloud}
rr.init("bench_startup")
rr.save(sys.argv[2])
rr.log("points", rr.Points3D(xyz), rr.AnyValues(intensity=np.abs(xyz[:, 2])))
rr.disconnect()
print(json.dumps({{"png_s": time.monotonic() - t0}}))
"""

API = """import sys, time, json, contextlib
t0 = float(sys.argv[1])
import numpy as np
from pointflow import Pipeline
{cloud}
cfg = {{"sources": [{{"transport": "api", "name": "api"}}], "ring": {{"max_points": len(xyz)}},
       "render": {{"size": [1280, 720], "color_by": "intensity", "output": {{"dir": None}}}}, "tracing": {{"enabled": False}}}}
with contextlib.redirect_stdout(sys.stderr), Pipeline.from_dict(cfg) as p:
    p.send(xyz, intensity=np.abs(xyz[:, 2]))
    p.wait(None, until=lambda: p.stats()["stages"]["render"].get("drawn_count", 0) >= len(xyz))
    p.save_frame(sys.argv[2])
    png_s = time.monotonic() - t0
print(json.dumps({{"png_s": png_s}}))
"""

START = """import sys, time, json
from pointflow import Pipeline
from pointflow.config import load_config
cfg = load_config(sys.argv[2])
extra = sys.argv[4:]
if "record" in extra:
    from pointflow.record.config import with_record_path
    cfg = with_record_path(cfg, sys.argv[3] + "/run.mcap")
if "serve" in extra:
    from pointflow.serve.config import with_serve
    cfg = with_serve(cfg, "127.0.0.1:0")
import contextlib
with contextlib.redirect_stdout(sys.stderr):
    p = Pipeline(cfg, out_dir=sys.argv[3])
    t = time.monotonic()
    p.start()
    start_s = time.monotonic() - t
    st = p.stats()["stages"]
    p.stop()
print(json.dumps({"start_s": start_s, "stages": {k: v.get("startup_ms", {}) for k, v in st.items()},
                  "supervisor": p.stats().get("startup_ms", {})}))
"""


def _py(code: str, root: Optional[Path], *args: str, timeout: float = 600) -> dict[str, Any]:
    """``python -c code t0 args...`` against ``root``'s pointflow (None: this checkout's);
    its JSON, with ``wall_s`` (spawn to exit) added."""
    t0 = time.monotonic()
    res = H.run_json(["-c", code, repr(t0), *args], root if root is not None else H.ROOT, timeout=timeout)
    res["wall_s"] = time.monotonic() - t0
    return res


def _demo_first_png(root: Optional[Path], config: str, timeout: float = 300) -> dict[str, Any]:
    """``pointflow run CONFIG`` until its first PNG exists (polled every 10 ms), then Ctrl-C."""
    root = root if root is not None else H.ROOT
    with tempfile.TemporaryDirectory(prefix="pf-startup-") as out:
        env = H.checkout_env(root)
        t0 = time.monotonic()
        p = subprocess.Popen([sys.executable, "-m", "pointflow.cli", "run", str(root / config), "--out", out, "-q"],
                             cwd=str(root), env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        png_s = None
        try:
            end = t0 + timeout
            while time.monotonic() < end and p.poll() is None:
                if any(f.endswith(".png") for f in os.listdir(out)):
                    png_s = time.monotonic() - t0
                    break
                time.sleep(0.01)
        finally:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
            try:
                p.wait(60)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        return {"png_s": png_s, "wall_s": time.monotonic() - t0}


def _rerun_available() -> bool:
    try:
        import importlib

        importlib.import_module("rerun")
        return True
    except ImportError:
        r = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "rerun-sdk"], capture_output=True, text=True)
        if r.returncode:
            print(f"rerun-sdk not installed ({r.stderr.strip().splitlines()[-1:] or 'pip failed'}): no rerun baseline",
                  file=sys.stderr)
            return False
        return True


def measure(trees: dict[str, Optional[Path]], rounds: int, with_rerun: bool, six: bool,
            n_show: int = N_SHOW, only: Optional[set[str]] = None) -> dict[str, Any]:
    cloud = _CLOUD.format(n=n_show)
    tmp = Path(tempfile.mkdtemp(prefix="pf-startup-png-"))
    runners: dict[str, Any] = {}
    for side, root in trees.items():
        runners[f"show:{side}"] = lambda r=root: _py(SHOW.format(cloud=cloud), r, str(tmp / "show.png"))
        runners[f"api:{side}"] = lambda r=root: _py(API.format(cloud=cloud), r, str(tmp / "api.png"))
        runners[f"demo:{side}"] = lambda r=root: _demo_first_png(r, "configs/demo.yaml")
        runners[f"start:{side}"] = lambda r=root: _py(START, r, "configs/demo.yaml", str(tmp / "start"))
        if six:
            runners[f"start6:{side}"] = lambda r=root: _py(START, r, "configs/demo.yaml", str(tmp / "start6"),
                                                           "record", "serve")
    runners["matplotlib"] = lambda: _py(MATPLOTLIB.format(cloud=cloud), None, str(tmp / "mpl.png"))
    if with_rerun:
        runners["rerun"] = lambda: _py(RERUN.format(cloud=cloud), None, str(tmp / "rr.rrd"))
    if only:
        runners = {k: fn for k, fn in runners.items() if k.split(":")[0] in only}
    print("warm-up round (caches filled)", flush=True)
    warm = {k: fn() for k, fn in runners.items()}

    def said(i: int, k: str, r: dict) -> None:
        fig = r.get("png_s", r.get("start_s"))
        print(f"  round {i}: {k:22s} {fig if fig is None else round(fig, 3)} s  ({H.uptime().split('load')[-1]})",
              flush=True)

    samples = H.interleave(runners, rounds, said)
    return {"warmup": warm, "samples": samples}


def summarise(samples: dict[str, list[dict]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, rs in samples.items():
        key = "start_s" if k.startswith("start") else "png_s"
        vals = [r[key] for r in rs if r.get(key) is not None]
        out[k] = {"figure": key, **(H.spread(vals) if vals else {"n": 0})}
        if k.startswith("start"):
            per: dict[str, dict[str, list]] = {}
            for r in rs:
                for cause, ms in r.get("supervisor", {}).items():  # before any stage: one bar
                    per.setdefault("(supervisor)", {}).setdefault(cause, []).append(ms)
                for stage, marks in r["stages"].items():
                    for cause, ms in marks.items():
                        per.setdefault(stage, {}).setdefault(cause, []).append(ms)
            out[k]["stages_ms"] = {s: {c: statistics.median(v) for c, v in d.items()} for s, d in per.items()}
    return out


CAUSES = ("prepare", "fork_server", "interpreter", "runtime", "module", "context", "setup")


def chart(summary: dict[str, Any], mach: dict[str, Any], path: Path) -> None:
    plt = H.pyplot()
    if plt is None:
        return
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(13, 5))
    keys = [k for k in summary if not k.startswith("start")]
    med = [summary[k].get("median", 0) for k in keys]
    a1.barh(keys, med, color=["tab:blue" if ":" in k else "tab:gray" for k in keys])
    for y, k in enumerate(keys):
        s = summary[k]
        if s.get("n"):
            a1.plot([s["min"], s["max"]], [y, y], color="k", lw=1)
            a1.text(s["median"], y, f" {s['median']:.2f} s", va="center")
    a1.axvline(1.5, color="r", ls="--", lw=1)
    a1.set_xlabel("seconds from the command's start to the picture (median, min-max)")
    a1.set_title("first picture")
    start = next((k for k in summary if k.startswith("start:head")), None) or next(
        (k for k in summary if k.startswith("start")), None)
    if start is not None:
        st = summary[start]["stages_ms"]
        names = list(st)
        left = [0.0] * len(names)
        for c in CAUSES:
            v = [st[n].get(c, 0.0) / 1000 for n in names]
            a2.barh(names, v, left=left, label=c)
            left = [a + b for a, b in zip(left, v)]
        a2.set_xlabel("seconds from spawn to first heartbeat (median)")
        a2.set_title(f"{start}: Pipeline.start() {summary[start]['median']:.2f} s (median)")
        a2.legend(fontsize=8)
    fig.suptitle(f"bench_startup.py, {H.machine_line(mach)}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    print(f"wrote {path}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--base", default=None, help="also measure this git revision (before/after in one run)")
    ap.add_argument("--no-rerun", action="store_true", help="skip the rerun-sdk baseline")
    ap.add_argument("--no-six", action="store_true", help="skip the 6-stage start (demo + record + serve)")
    ap.add_argument("--show-points", type=int, default=N_SHOW, help="points of the show / api / matplotlib cloud")
    ap.add_argument("--only", default="", help="comma-separated: show, api, demo, start, start6, matplotlib, rerun")
    ap.add_argument("--out", default=str(H.RESULTS / "startup.json"))
    a = ap.parse_args()
    mach = H.machine()
    with_rerun = not a.no_rerun and _rerun_available()
    with contextlib.ExitStack() as stack:
        trees: dict[str, Optional[Path]] = {"head": None}
        if a.base:
            trees["base"] = stack.enter_context(H.revision_tree(a.base))
        res = measure(trees, a.rounds, with_rerun, not a.no_six, a.show_points,
                      {x.strip() for x in a.only.split(",") if x.strip()} or None)
    H.machine_done(mach)
    summary = summarise(res["samples"])
    out = {"command": H.command(), "machine": mach, "base": a.base, "rounds": a.rounds, "n_show": a.show_points,
           "rerun": with_rerun, "summary": summary, **res}
    H.write_result(a.out, out)
    chart(summary, mach, Path(a.out).with_suffix(".png"))
    for k, s in summary.items():
        if s.get("n"):
            print(f"{k:22s} median {s['median']:.3f} s  ({s['min']:.3f}-{s['max']:.3f}, n={s['n']})")


if __name__ == "__main__":
    main()
