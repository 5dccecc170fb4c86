"""Restart latency: SIGKILL a stage of the demo pipeline and time kill -> new incarnation
reported in -> next frame, with prepared standbys (``supervisor.standby: true``, the
default) and without, alternated in the same run (issue 19).

    XDG_RUNTIME_DIR=/tmp/xdg .venv/bin/python bench/bench_restart.py [--kills 3] [--rounds 2]

The demo pipeline (configs/demo.yaml: wgpu compute on lavapipe here, 1280x720, 1M-point
ring), no PNGs. Each kill waits ``--gap`` seconds after the previous restart so the next
standby is ready (it is prepared 5 s after the last stage reported in). Writes
bench/results/restart.json.
"""
from __future__ import annotations

import argparse
import os
import signal
import statistics
import time

import yaml

import _harness as H
from pointflow import Pipeline

ROOT = H.ROOT


def one_run(stage: str, standby: bool, kills: int, gap: float) -> list[dict]:
    cfg = yaml.safe_load((ROOT / "configs" / "demo.yaml").read_text())
    cfg["render"]["output"] = {"dir": None}
    cfg["supervisor"] = {"max_restarts": 100, "standby": standby}
    out = []
    with Pipeline.from_dict(cfg, out_dir=None) as pipe:
        time.sleep(gap)
        for _ in range(kills):
            s = pipe.stats()
            pid, had_standby = s["stages"][stage]["pid"], s["stages"][stage].get("standby_pid")
            t_kill = time.monotonic()
            os.kill(pid, signal.SIGKILL)
            ready = frame = None
            f0 = None
            while time.monotonic() - t_kill < 60:
                s = pipe.stats()
                st = s["stages"][stage]
                if ready is None and st["pid"] != pid and st["ready"]:
                    ready, f0 = time.monotonic() - t_kill, s["frames"]
                if ready is not None and s["frames"] > f0:
                    frame = time.monotonic() - t_kill
                    break
                time.sleep(0.01)
            out.append({"stage": stage, "standby": standby, "standby_ready": bool(had_standby),
                        "ready_s": None if ready is None else round(ready, 3),
                        "frame_s": None if frame is None else round(frame, 3), "load": os.getloadavg()[0]})
            print(f"  {stage:8s} standby {'on ' if standby else 'off'}: reported in after {out[-1]['ready_s']} s, "
                  f"next frame after {out[-1]['frame_s']} s (load {out[-1]['load']:.1f})", flush=True)
            time.sleep(gap)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stages", default="render,cadence")
    ap.add_argument("--kills", type=int, default=3, help="kills per run")
    ap.add_argument("--rounds", type=int, default=2, help="runs per (stage, standby) pair, alternated")
    ap.add_argument("--gap", type=float, default=12.0)
    ap.add_argument("--out", default=str(H.RESULTS / "restart.json"))
    args = ap.parse_args()
    machine = H.machine()
    rows: list[dict] = []
    for r in range(args.rounds):
        for stage in args.stages.split(","):
            for standby in (False, True):
                rows += one_run(stage, standby, args.kills, args.gap)
    summary = {}
    for stage in args.stages.split(","):
        for standby in (False, True):
            sel = [x for x in rows if x["stage"] == stage and x["standby"] == standby and x["frame_s"] is not None]
            if sel:
                summary[f"{stage}_standby_{'on' if standby else 'off'}"] = {
                    "kills": len(sel), "median_ready_s": round(statistics.median(x["ready_s"] for x in sel), 3),
                    "median_frame_s": round(statistics.median(x["frame_s"] for x in sel), 3),
                    "max_frame_s": max(x["frame_s"] for x in sel)}
    print(f"\n{'stage, standby':24s} {'kills':>5s} {'report-in s (median)':>21s} {'next frame s (median)':>22s} {'max':>6s}")
    for k, v in summary.items():
        print(f"{k:24s} {v['kills']:5d} {v['median_ready_s']:21.2f} {v['median_frame_s']:22.2f} {v['max_frame_s']:6.2f}")
    H.write_result(args.out, {"benchmark": "restart", "summary": summary, "kills": rows,
                              "machine": H.machine_done(machine), "command": H.command()}, indent=1)


if __name__ == "__main__":
    main()
