"""Drag to first frame, and where its tail comes from (issue 39, item 7): a still view at
800x600, a turn (``orbit`` 3 deg) sent by the client, the time to the first frame that
shows it, cut into its parts with the clocks of the processes (one machine: one
CLOCK_MONOTONIC):

* ``to_render`` — client -> view server -> render stage, until the turn is applied
  (the reply's ``changed_ns``); of it ``to_serve`` (client -> the view server's event
  loop, the reply's ``served_ns``) and ``serve_to_render`` (zmq and the render loop);
* ``wait``      — applied -> the view's draw starts (the loop busy with something else:
  the main view's own frame, a handoff, credit);
* ``draw``      — the view's draw and read-back (``frame_ms``);
* ``to_client`` — drawn -> the client has the encoded frame (zmq, the view server's event
  loop, the encoder, the socket); ``encode`` is the encoder's part.

``--before REV`` runs the same turns against revision REV's pointflow too (``git archive``
into a temporary tree), the two sides interleaved round by round (ABBA), so the load hits
both alike; each side's p50/p99 and the ratio after/before are written.

    python bench/bench_drag.py --before main          # ~6 min on 2 busy cores
    python bench/bench_drag.py --turns 40 --rounds 2  # quicker

Writes ``bench/results/drag.json``; ``uptime`` before and after.
"""
from __future__ import annotations

import argparse
import json
import random
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import _harness  # sets XDG_RUNTIME_DIR before pointflow is imported

RESULTS = _harness.RESULTS
HERE = Path(__file__).resolve()


def one(points: int, size, turns: int) -> dict:
    """One pipeline (this process's pointflow), ``turns`` turns; each turn's parts in ms."""
    from _harness.views import Client
    from _harness.views import base_url as _base_url
    from _harness.views import config as _config
    from _harness.views import render_stats as _render
    from _harness.views import scene as _scene

    from pointflow import Pipeline

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        cfg = _config(_scene(tmp, points), points, size, "cpu", orbit=0.0)
        with Pipeline.from_dict(cfg, out_dir=tmp) as pipe:
            pipe.wait(120, until=lambda: _render(pipe).get("drawn_count", 0) >= points)
            # the compiled raster (a fresh tree compiles it beside the stage: minutes here)
            pipe.wait(900, until=lambda: _render(pipe).get("raster") not in ("compiling", None))
            c = Client(_base_url(pipe))
            try:
                time.sleep(1.5)
                for i in range(turns):
                    t0, rep, hit = c.turn(1000 + i)
                    if hit is not None:
                        row = {"lat": (hit["t"] - t0) * 1e3, "draw": hit.get("frame_ms"),
                               "encode": hit.get("encode_ms")}
                        ch = rep.get("changed_ns")
                        if ch:
                            row["to_render"] = ch / 1e6 - t0 * 1e3
                        if ch and rep.get("served_ns"):
                            row["to_serve"] = rep["served_ns"] / 1e6 - t0 * 1e3
                            row["serve_to_render"] = (ch - rep["served_ns"]) / 1e6
                        if hit.get("t_ns") and ch:
                            start = hit["t_ns"] / 1e6 - (hit.get("frame_ms") or 0.0)
                            row["wait"] = start - ch / 1e6
                            row["to_client"] = hit["t"] * 1e3 - hit["t_ns"] / 1e6
                        rows.append(row)
                    time.sleep(random.uniform(0.35, 0.6))  # it settles: the still (PNG) frame comes
            finally:
                c.close()
    return {"rows": rows}


def _stats(rows: list[dict]) -> dict:
    out = {"turns": len(rows)}
    lat = np.array([r["lat"] for r in rows])
    if not lat.size:
        return out
    out.update(p50_ms=float(np.percentile(lat, 50)), p99_ms=float(np.percentile(lat, 99)),
               p90_ms=float(np.percentile(lat, 90)), max_ms=float(lat.max()))
    draw = [r["draw"] for r in rows if r.get("draw") is not None]
    enc = [r["encode"] for r in rows if r.get("encode") is not None]
    if draw and enc:
        out["budget_ms"] = 2 * float(np.median(draw)) + float(np.median(enc))
    # the parts: median over all turns, and their mean over the slowest 5 % (the tail)
    tail = sorted(rows, key=lambda r: r["lat"])[-max(1, len(rows) // 20):]
    for k in ("to_render", "to_serve", "serve_to_render", "wait", "draw", "encode", "to_client"):
        vals = [r[k] for r in rows if r.get(k) is not None]
        if vals:
            out[f"{k}_median_ms"] = float(np.median(vals))
            tv = [r[k] for r in tail if r.get(k) is not None]
            out[f"{k}_tail_mean_ms"] = float(np.mean(tv)) if tv else None
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=300_000)
    ap.add_argument("--size", default="800x600")
    ap.add_argument("--turns", type=int, default=60, help="turns per side and round")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--before", default=None, help="a revision to compare with (interleaved)")
    ap.add_argument("--one", action="store_true", help=argparse.SUPPRESS)  # a child: one side, one round
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    if args.one:
        print(json.dumps(one(args.points, size, args.turns)))
        return
    mach = _harness.machine(command=_harness.command())
    child = [str(HERE), "--one", "--points", str(args.points), "--size", args.size, "--turns", str(args.turns)]
    tree_cm = _harness.revision_tree(args.before) if args.before else None
    tree = tree_cm.__enter__() if tree_cm else None
    try:
        runners = {"after": lambda: _harness.run_json(child, _harness.ROOT, timeout=1200)}
        if tree is not None:
            runners["before"] = lambda: _harness.run_json(child, tree, timeout=1200)
        res = _harness.interleave(runners, args.rounds,
                                  on_result=lambda i, k, r: print(i, k, json.dumps(_stats(r["rows"])), flush=True))
    finally:
        if tree_cm:
            tree_cm.__exit__(None, None, None)
    _harness.machine_done(mach)
    out = {"machine": mach, "uptime_before": mach["uptime_before"], "uptime_after": mach["uptime_after"],
           "before_revision": _harness.resolve_revision(args.before) if args.before else None,
           "size": list(size), "points": args.points, "turns_per_round": args.turns, "rounds": args.rounds}
    for k, rounds in res.items():
        rows = [r for rr in rounds for r in rr["rows"]]
        out[k] = _stats(rows) | {"per_round": [_stats(rr["rows"]) for rr in rounds],
                                 "latency_ms": [r["lat"] for r in rows], "rows": rows}
    if "before" in out and out["before"].get("p99_ms"):
        out["after_over_before"] = {p: out["after"][p] / out["before"][p] for p in ("p50_ms", "p90_ms", "p99_ms")}
    _harness.write_result(Path(args.out) if args.out else RESULTS / "drag.json", out, 1)


if __name__ == "__main__":
    sys.exit(main())
