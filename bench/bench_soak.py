"""Soak: memory stays bounded while a source outruns the ring for a long time; with
``--minutes``, the chaos soak (issue 19).

A synthetic source replays cached scans as fast as it can (many times the ring's capacity
per second) into a small ring, rendered by the cpu tier. Every second the supervisor's
stats are sampled: per-stage RSS, ring fill, ingest counts. The baseline is each stage's
median RSS over the first third after the warm-up (same run); the result is the median over
the last third divided by it (1.0 = no growth) and the peak, plus the accounting check. Prints a table and writes bench/results/soak.json.

    .venv/bin/python bench/bench_soak.py --seconds 60

Chaos soak (``--minutes 10`` or ``--minutes 60``): the demo pipeline (configs/demo.yaml:
synthetic lidar 100k points/scan at 10 Hz, 1M-point ring, 60 Hz cadence, render backend
auto, 1280x720; no PNGs) with a random stage SIGKILLed every ``--kill-every`` s (30) and a
random stage frozen with SIGSTOP for ``--freeze-s`` (3 s, past ``hung_after_ms``) every
``--freeze-every`` s (150). The caller only samples ``stats()`` (supervision is the
background thread's). Checks: every kill restarted; frames resume within 2 s of each
restarted stage reporting in; frames never stop for more than 2 s after a kill (the
longest gap without a new frame from the kill until frames flow again); each stage's RSS
late vs early within 5% (medians of the last and first thirds after the warm-up); the
accounting identities exact at the end, and in every 0.1-s sample of ``stats()``
(``accounting_exact_in_every_sample``); nothing left in /dev/shm, the run directory or the
process table (standby processes included). Prints per kill: whether a standby was ready,
report-in time, time to the next frame from report-in and from the kill, longest gap.
Writes bench/results/soak_chaos_<M>min.json and .png (RSS and frames over time).

    .venv/bin/python bench/bench_soak.py --minutes 10

``--busy-loops N`` runs N ``while True: pass`` processes beside it at the default priority
(the load under which issue 31 asked for exact accounting) and ends them with the run; the
result file is then soak_chaos_<M>min_busy<N>.json. The load average is sampled with the
stats.

    .venv/bin/python bench/bench_soak.py --minutes 30 --busy-loops 2
"""
from __future__ import annotations

import argparse
import json
import os
import random
import signal
import time

import numpy as np

import _harness as H
from pointflow import Pipeline

RESULTS = H.RESULTS


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--warmup", type=float, default=10.0)
    ap.add_argument("--ring", type=int, default=200_000)
    ap.add_argument("--minutes", type=float, default=None, help="chaos soak of this many minutes")
    ap.add_argument("--kill-every", type=float, default=30.0)
    ap.add_argument("--freeze-every", type=float, default=150.0)
    ap.add_argument("--freeze-s", type=float, default=3.0)
    ap.add_argument("--seed", type=int, default=19)
    ap.add_argument("--busy-loops", type=int, default=0,
                    help="chaos soak: run this many `while True: pass` processes beside it (load)")
    args = ap.parse_args()
    if args.minutes is not None:
        chaos(args)
        return
    machine = H.machine()
    cfg = {
        "source": {"transport": "synthetic",
                   "options": {"points_per_scan": 100_000, "realtime": False, "cache_scans": 4}},
        "ring": {"max_points": args.ring},
        "cadence": {"target_hz": 30},
        "render": {"backend": "cpu", "size": [320, 240], "output": {"dir": None}},
    }
    samples = []
    pipe = Pipeline.from_dict(cfg, out_dir=None)
    with pipe:
        t0 = time.monotonic()
        next_t = t0
        while time.monotonic() - t0 < args.seconds:
            pipe.wait(max(0.0, next_t - time.monotonic()))
            next_t += 1.0
            st = pipe.stats()
            samples.append({
                "t": round(time.monotonic() - t0, 2),
                "rss_mb": {n: round(s.get("rss_bytes", 0) / 2**20, 1) for n, s in st["stages"].items()},
                "ring_points": (st.get("ring") or {}).get("total_points"),
                "ingest_in": st["stages"]["ingest"]["points_in"],
                "frames": st["frames"],
            })
    final = pipe.stats()
    warm = [s for s in samples if s["t"] >= args.warmup] or samples
    first, last = warm[0], warm[-1]
    # RSS breathes with the allocator (chunks in flight); a leak shows as the late median
    # rising above the early one, so compare medians of the first and last thirds
    third = max(1, len(warm) // 3)
    med = lambda rows, n: float(np.median([r["rss_mb"][n] for r in rows]))
    early = {n: med(warm[:third], n) for n in last["rss_mb"]}
    late = {n: med(warm[-third:], n) for n in last["rss_mb"]}
    growth = {n: round(late[n] / early[n], 3) if early[n] else None for n in last["rss_mb"]}
    peak = {n: max(s["rss_mb"][n] for s in warm) for n in last["rss_mb"]}
    secs = last["t"] - first["t"]
    rate = (last["ingest_in"] - first["ingest_in"]) / secs if secs > 0 else 0.0
    out = {
        "benchmark": "soak", "seconds": args.seconds, "warmup_s": args.warmup, "ring_points": args.ring,
        "machine": H.machine_done(machine), "command": H.command(),
        "ingest_points_per_s": round(rate), "ring_turnovers": round((last["ingest_in"] - first["ingest_in"]) / args.ring, 1),
        "rss_mb_early_median": early, "rss_mb_late_median": late, "rss_mb_peak": peak,
        "rss_growth_ratio_late_vs_early": growth, "accounting": final.get("accounting"), "frames": final.get("frames"),
        "samples": samples,
    }
    H.write_result(RESULTS / "soak.json", out)
    print(f"soak: {secs:.0f} s after a {args.warmup:.0f} s warm-up, {rate / 1e6:.1f} M points/s into a "
          f"{args.ring:,}-point ring ({out['ring_turnovers']} turnovers), {out['frames']} frames")
    print(f"{'stage':10s} {'early median MB':>16s} {'late median MB':>15s} {'peak MB':>8s} {'late/early':>10s}")
    for n in last["rss_mb"]:
        print(f"{n:10s} {early[n]:16.1f} {late[n]:15.1f} {peak[n]:8.1f} {growth[n]!s:>10s}")
    acc = final.get("accounting") or {}
    print(f"accounting: ingest balanced {acc.get('ingest_balanced')}, ring agrees {acc.get('ring_agrees')}, "
          f"lost before ingest {acc.get('lost_before_ingest')}")


STAGES = ("source", "ingest", "cadence", "render")
#: Frames must flow again within this long after a restarted stage reports in.
RESUME_LIMIT_S = 2.0
RSS_LIMIT = 1.05


def _alive(pid: int) -> bool:
    import psutil

    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def chaos(args) -> None:
    import yaml

    rng = random.Random(args.seed)
    root = H.ROOT
    cfg = yaml.safe_load((root / "configs" / "demo.yaml").read_text())
    cfg["render"]["output"] = {"dir": None}
    cfg["supervisor"] = {"max_restarts": 100_000}
    total_s = args.minutes * 60
    warm = min(30.0, total_s / 6)
    samples: list[dict] = []
    kills: list[dict] = []
    freezes: list[dict] = []
    pids_seen: set[int] = set()
    import subprocess
    import sys

    machine = H.machine(busy_loops=args.busy_loops, nice=os.nice(0))
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.busy_loops)]
    pipe = Pipeline.from_dict(cfg, out_dir=None)
    try:
        pipe.start()
    except BaseException:
        for p in busy:
            p.kill()
        raise
    sup = pipe.supervisor
    run_dir = sup.run_dir
    t0 = time.monotonic()
    next_kill = warm
    next_freeze = warm + args.kill_every / 2
    frozen = None  # (pid, until)
    try:
        while (t := time.monotonic() - t0) < total_s:
            st = pipe.stats()
            stages = st["stages"]
            pids_seen.update(v["pid"] for v in stages.values() if v.get("pid"))
            pids_seen.update(v["standby_pid"] for v in stages.values() if v.get("standby_pid"))
            a = st.get("accounting") or {}
            samples.append({"t": round(t, 2), "frames": st["frames"], "load1": round(os.getloadavg()[0], 2),
                            # the identities in this live sample (issue 31: they hold in every one)
                            "exact": bool(a.get("ingest_balanced") and a.get("ring_agrees") and a.get("sources_balanced")),
                            "ring_ahead": (a.get("ring_written_now") or 0) - (a.get("ring_written") or 0),
                            "rss_mb": {n: round(v.get("rss_bytes", 0) / 2**20, 1) for n, v in stages.items()},
                            "pid": {n: v["pid"] for n, v in stages.items()},
                            "ready": {n: bool(v.get("ready")) and bool(v.get("alive")) for n, v in stages.items()}})
            if frozen and t >= frozen[1]:
                try:
                    os.kill(frozen[0], signal.SIGCONT)
                except ProcessLookupError:
                    pass  # the supervisor found it hung and replaced it
                frozen = None
            if t >= next_kill and frozen is None:
                next_kill += args.kill_every
                if live := _live_stage(rng, samples, stages):
                    name, pid = live
                    os.kill(pid, signal.SIGKILL)
                    kills.append({"t": round(t, 2), "stage": name, "pid": pid, "frames": st["frames"],
                                  "standby": stages[name].get("standby_pid")})
                    print(f"{t:7.1f} s  SIGKILL {name} (pid {pid})", flush=True)
            if t >= next_freeze and frozen is None:
                next_freeze += args.freeze_every
                if live := _live_stage(rng, samples, stages):
                    name, pid = live
                    os.kill(pid, signal.SIGSTOP)
                    frozen = (pid, t + args.freeze_s)
                    freezes.append({"t": round(t, 2), "stage": name, "pid": pid, "seconds": args.freeze_s})
                    print(f"{t:7.1f} s  SIGSTOP {name} (pid {pid}) for {args.freeze_s:.0f} s", flush=True)
            time.sleep(0.1)
    finally:
        if frozen:
            try:
                os.kill(frozen[0], signal.SIGCONT)
            except ProcessLookupError:
                pass
        segments = list(sup.segments)
        final = pipe.stop()
        for p in busy:
            p.kill()
            p.wait()
    pids_seen.update(v["pid"] for v in final["stages"].values() if v.get("pid"))
    pids_seen.update(v["standby_pid"] for v in final["stages"].values() if v.get("standby_pid"))
    time.sleep(1.0)
    args.machine = machine
    _chaos_report(args, cfg, samples, kills, freezes, final, segments, run_dir, pids_seen, warm)


def _live_stage(rng, samples, stages) -> tuple[str, int] | None:
    """A stage (name, pid) chosen at random among those the last sample saw ready."""
    live = [n for n in STAGES if samples[-1]["ready"].get(n)]
    if not live:
        return None
    name = rng.choice(live)
    return name, stages[name]["pid"]


def _first(samples, t_from, pred):
    return next((s for s in samples if s["t"] >= t_from and pred(s)), None)


def _chaos_report(args, cfg, samples, kills, freezes, final, segments, run_dir, pids_seen, warm) -> None:
    events = final["events"]
    # every kill: the supervisor saw the death, a new incarnation reported in, frames resumed
    for k in kills:
        ev = next((e for e in events if e["stage"] == k["stage"] and e["pid"] == k["pid"]), None)
        k["restart_event"] = ev is not None and ev.get("action") == "restart"
        back = _first(samples, k["t"], lambda s, k=k: s["pid"][k["stage"]] != k["pid"] and s["ready"][k["stage"]])
        k["back_after_s"] = round(back["t"] - k["t"], 2) if back else None
        if back:
            f0 = back["frames"]
            resumed = _first(samples, back["t"], lambda s, f0=f0: s["frames"] > f0)
            k["frames_resumed_after_back_s"] = round(resumed["t"] - back["t"], 2) if resumed else None
            k["frames_resumed_after_kill_s"] = round(resumed["t"] - k["t"], 2) if resumed else None
        else:
            k["frames_resumed_after_back_s"] = k["frames_resumed_after_kill_s"] = None
    # the longest time without a new frame from the kill until frames flow again after the
    # restart (a source or ingest kill need not stop the frames at all; a render or cadence
    # kill does until the new one draws)
    for k in kills:
        end = k["t"] + (k["frames_resumed_after_kill_s"] if k["frames_resumed_after_kill_s"] is not None else 60.0)
        last_t, last_f, gap = k["t"], None, 0.0
        for s in samples:
            if s["t"] < k["t"]:
                continue
            if last_f is None:
                last_f = s["frames"]
            elif s["frames"] > last_f:
                gap, last_t, last_f = max(gap, s["t"] - last_t), s["t"], s["frames"]
            if s["t"] > end:
                break
        k["longest_frame_gap_s"] = round(gap, 2)
    for f in freezes:
        f["replaced_as_hung"] = any(e["stage"] == f["stage"] and e["pid"] == f["pid"] for e in events)
    # the longest stretch without a new frame, outside [kill or freeze, back + 2 s]
    windows = []
    for k in kills:
        windows.append((k["t"], k["t"] + (k["back_after_s"] or 1e9) + RESUME_LIMIT_S))
    for f in freezes:
        windows.append((f["t"], f["t"] + f["seconds"] + 30.0))
    steady_gap, last_t, last_f = 0.0, None, None
    for s in samples:
        if s["t"] < warm:
            continue
        if last_f is None or s["frames"] > last_f:
            if last_t is not None and not any(a <= s["t"] and last_t <= b for a, b in windows):
                steady_gap = max(steady_gap, s["t"] - last_t)
            last_t, last_f = s["t"], s["frames"]
    # RSS: medians of the first and last thirds after the warm-up, per stage
    rows = [s for s in samples if s["t"] >= warm]
    third = max(1, len(rows) // 3)
    med = lambda part, n: float(np.median([r["rss_mb"][n] for r in part if r["rss_mb"].get(n)] or [0]))
    names = list(final["stages"])
    early = {n: med(rows[:third], n) for n in names}
    late = {n: med(rows[-third:], n) for n in names}
    growth = {n: round(late[n] / early[n], 3) if early[n] else None for n in names}
    acc = final.get("accounting") or {}
    exact = bool(acc.get("ingest_balanced") and acc.get("ring_agrees") and acc.get("sources_balanced"))
    leftover_shm = [s for s in segments if os.path.exists(os.path.join("/dev/shm", s))]
    leftover_procs = sorted(p for p in pids_seen if _alive(p))
    resumes = [k["frames_resumed_after_back_s"] for k in kills]
    from_kill = [k["frames_resumed_after_kill_s"] for k in kills]
    checks = {
        "every_kill_restarted": all(k["restart_event"] and k["back_after_s"] is not None for k in kills),
        "frames_resume_within_2s_of_restart": all(r is not None and r <= RESUME_LIMIT_S for r in resumes),
        "frames_never_stop_over_2s_after_a_kill": all(k["longest_frame_gap_s"] <= RESUME_LIMIT_S
                                                      and k["frames_resumed_after_kill_s"] is not None for k in kills),
        "rss_flat_within_5pct": all(g is None or g <= RSS_LIMIT for g in growth.values()),
        "accounting_exact": exact,
        "accounting_exact_in_every_sample": all(r["exact"] for r in samples),
        "nothing_left_in_dev_shm": not leftover_shm,
        "run_dir_removed": not (run_dir and os.path.exists(run_dir)),
        "no_process_left": not leftover_procs,
    }
    out = {
        "benchmark": "soak_chaos", "minutes": args.minutes, "kill_every_s": args.kill_every,
        "freeze_every_s": args.freeze_every, "freeze_s": args.freeze_s, "seed": args.seed, "warmup_s": warm,
        "machine": {**H.machine_done(args.machine),
                    "load1_min_max": [min(s["load1"] for s in samples), max(s["load1"] for s in samples)]},
        "command": H.command(),
        "config": cfg, "checks": checks, "passed": all(checks.values()),
        "kills": kills, "freezes": freezes, "events": events,
        "frames_total": final.get("frames"), "frames_per_s": round(final.get("frames", 0) / max(1.0, samples[-1]["t"]), 2),
        "max_frames_resumed_after_restart_s": max((r for r in resumes if r is not None), default=None),
        "median_frames_resumed_after_restart_s": float(np.median([r for r in resumes if r is not None])) if any(
            r is not None for r in resumes) else None,
        "frames_resumed_within_2s_of_restart": sum(1 for r in resumes if r is not None and r <= RESUME_LIMIT_S),
        "frames_resumed_within_2s_of_kill": sum(1 for r in from_kill if r is not None and r <= RESUME_LIMIT_S),
        "median_frames_resumed_after_kill_s": float(np.median([r for r in from_kill if r is not None])) if any(
            r is not None for r in from_kill) else None,
        "max_frames_resumed_after_kill_s": max((r for r in from_kill if r is not None), default=None),
        "frames_never_stopped_over_2s": sum(1 for k in kills if k["longest_frame_gap_s"] <= RESUME_LIMIT_S),
        "max_frame_gap_after_kill_s": max((k["longest_frame_gap_s"] for k in kills), default=None),
        "max_steady_frame_gap_s": round(steady_gap, 2),
        "rss_mb_early_median": early, "rss_mb_late_median": late, "rss_growth_ratio_late_vs_early": growth,
        "accounting": acc, "leftover_shm": leftover_shm, "leftover_pids": leftover_procs,
        "live_samples": len(samples), "live_samples_exact": sum(1 for r in samples if r["exact"]),
        "live_samples_ring_ahead_of_report": sum(1 for r in samples if r["ring_ahead"] > 0),
        "samples_note": "one sample per second (t, frames, rss_mb, pid per stage); the chart uses all 0.1 s samples",
    }
    rows_1s = [{k: v for k, v in r.items() if k not in ("ready", "exact", "ring_ahead")} for r in samples[::10]]
    tag = f"soak_chaos_{args.minutes:g}min" + (f"_busy{args.busy_loops}" if args.busy_loops else "")
    RESULTS.mkdir(exist_ok=True)
    txt = json.dumps(out, indent=1, default=str)  # then one compact line per sample
    txt = txt[:-2] + ',\n "samples": [\n' + ",\n".join("  " + json.dumps(r, separators=(",", ":")) for r in rows_1s) + "\n ]\n}\n"
    (RESULTS / f"{tag}.json").write_text(txt)
    _chaos_chart(RESULTS / f"{tag}.png", samples, kills, freezes, names, args)
    print(f"chaos soak {args.minutes:g} min: {len(kills)} kills, {len(freezes)} freezes, {final.get('frames')} frames "
          f"({out['frames_per_s']}/s)")
    print(f"frames resumed after a restart: median {out['median_frames_resumed_after_restart_s']} s, "
          f"max {out['max_frames_resumed_after_restart_s']} s (limit {RESUME_LIMIT_S}); "
          f"longest steady gap {out['max_steady_frame_gap_s']} s")
    print(f"{'t s':>7s} {'stage':8s} {'standby':>7s} {'back s':>7s} {'frame after back s':>19s} {'frame after kill s':>19s}"
          f" {'longest gap s':>14s}")
    for k in kills:
        print(f"{k['t']:7.1f} {k['stage']:8s} {'yes' if k.get('standby') else 'no':>7s} {k['back_after_s']!s:>7s} "
              f"{k['frames_resumed_after_back_s']!s:>19s} {k['frames_resumed_after_kill_s']!s:>19s} "
              f"{k['longest_frame_gap_s']!s:>14s}")
    print(f"frames never stopped for more than {RESUME_LIMIT_S:g} s after {out['frames_never_stopped_over_2s']} of "
          f"{len(kills)} kills (longest gap {out['max_frame_gap_after_kill_s']} s)")
    print(f"frames resumed within {RESUME_LIMIT_S:g} s: {out['frames_resumed_within_2s_of_restart']} of {len(kills)} "
          f"after the restarted stage reported in, {out['frames_resumed_within_2s_of_kill']} of {len(kills)} after the kill "
          f"(median {out['median_frames_resumed_after_kill_s']} s, max {out['max_frames_resumed_after_kill_s']} s)")
    print("RSS late/early:", ", ".join(f"{n} {g}" for n, g in growth.items()))
    print(f"live samples with every identity exact: {out['live_samples_exact']} of {out['live_samples']} "
          f"({out['live_samples_ring_ahead_of_report']} taken while the ring ran ahead of ingest's last report)")
    print(f"accounting: received {acc.get('ingest_received'):,} = written {acc.get('ingest_written'):,} + dropped "
          f"{acc.get('ingest_dropped'):,}; ring {acc.get('ring_written'):,}; reconciled from the ring "
          f"{acc.get('ingest_unreported_written'):,}; sources {acc.get('sources_received'):,} = "
          f"{acc.get('sources_forwarded'):,} + {acc.get('sources_dropped'):,}")
    for k, v in checks.items():
        print(f"  {'ok  ' if v else 'FAIL'} {k}")
    print(f"wrote {RESULTS / (tag + '.json')} and .png")


def _chaos_chart(path, samples, kills, freezes, names, args) -> None:
    if (plt := H.pyplot()) is None:
        return
    t = np.array([s["t"] for s in samples])
    f = np.array([s["frames"] for s in samples], dtype=float)
    # frames per second over 2 s windows
    step = 2.0
    edges = np.arange(0, t[-1] + step, step)
    fps = [(np.interp(b, t, f) - np.interp(a, t, f)) / step for a, b in zip(edges[:-1], edges[1:])]
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(11, 6.5), sharex=True)
    ax1.plot(edges[1:], fps, lw=1, color="k")
    ax1.set_ylabel("frames/s (2 s windows)")
    colors = {"source": "tab:blue", "ingest": "tab:orange", "cadence": "tab:green", "render": "tab:red"}
    for k in kills:
        for ax in (ax1, ax2):
            ax.axvline(k["t"], color=colors.get(k["stage"], "grey"), lw=0.8, alpha=0.7)
    for fz in freezes:
        for ax in (ax1, ax2):
            ax.axvspan(fz["t"], fz["t"] + fz["seconds"], color=colors.get(fz["stage"], "grey"), alpha=0.25)
    for n in names:
        ax2.plot(t, [s["rss_mb"].get(n, 0) for s in samples], lw=1, label=n, color=colors.get(n))
    ax2.set_ylabel("RSS MB")
    ax2.set_xlabel("seconds (lines: SIGKILL of the stage of that colour; bands: SIGSTOP)")
    ax2.legend(loc="upper left", ncol=4, fontsize=8)
    fig.suptitle(f"chaos soak, demo pipeline, {args.minutes:g} min: kill every {args.kill_every:g} s, "
                 f"freeze {args.freeze_s:g} s every {args.freeze_every:g} s (2-core shared VM, lavapipe)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


if __name__ == "__main__":
    main()
