"""Cadence benchmark: achieved tick rate and tick jitter at 30/60/120 Hz, idle and under load.

Real processes: a cadence process runs the stage's :class:`~pointflow.cadence.process.Cadence`
loop (ring → slab snapshot → ZeroMQ handoff) against a 1M-point ring; a null renderer
process takes every handoff and releases it at once; under ``load`` a third process pushes
20k-point chunks into the ring as fast as it can (each tick then copies the dirty ranges).

Jitter = how late a tick is served after its absolute deadline. Baseline, measured in the
same run under the same conditions: the naive loop ``sleep(period); publish()`` (relative
sleeps), whose rate drifts by the work + oversleep per tick. Targets (issue 5): achieved rate
within 1 % of target; p99 jitter <= 2 ms at 60 Hz idle.

    XDG_RUNTIME_DIR=/tmp/xdg .venv/bin/python bench/bench_cadence.py [--seconds 5] [--out bench/results/cadence.json]
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import time

import numpy as np

import _harness as H

RING_POINTS = 1_000_000
CHUNK = 20_000
WARMUP_S = 0.5


def _cfg(hz: float):
    from pointflow.config import load_config

    return load_config({"source": {"transport": "synthetic"}, "cadence": {"target_hz": hz},
                        "policy": {"tier": "M"}, "ring": {"max_points": RING_POINTS}})


def loader(ring_name: str, stop, out) -> None:
    """Push synthetic chunks into the ring as fast as possible."""
    from pointflow.ring import PointRing

    ring = PointRing.attach(ring_name)
    rng = np.random.default_rng(1)
    pos = rng.uniform(-50, 50, (CHUNK, 3))
    inten = rng.random(CHUNK).astype(np.float32)
    n = 0
    t0 = time.perf_counter()
    tid = 1
    while not stop.is_set():
        ring.push(pos, trace_id=tid, intensity=inten)
        n += CHUNK
        tid += 1
    out.put({"points_per_s": n / (time.perf_counter() - t0)})
    ring.close()


def null_renderer(slab_names, ep_frames: str, ep_release: str, stop) -> None:
    import zmq

    from pointflow.cadence.messages import encode_hello
    from pointflow.ring import SlabPair, SlabReader

    slabs = SlabPair.attach(slab_names)
    z = zmq.Context()
    pull = z.socket(zmq.PULL); pull.bind(ep_frames)
    push = z.socket(zmq.PUSH); push.connect(ep_release)
    reader = SlabReader(slabs, pull, push)
    push.send_multipart(encode_hello(os.getpid()))
    while not stop.is_set():
        if reader.recv(50):
            reader.release()
    for s in (pull, push):
        s.close(0)
    z.term()
    slabs.close()


def cadence(ring_name, slab_names, ep_frames, ep_release, hz, mode, seconds, out) -> None:
    import zmq

    from pointflow.cadence.policy import resolve_policy
    from pointflow.cadence.process import Cadence
    from pointflow.ring import PointRing, SlabPair

    cfg = _cfg(hz)
    ring = PointRing.attach(ring_name)
    slabs = SlabPair.attach(slab_names)
    z = zmq.Context()
    rel = z.socket(zmq.PULL); rel.bind(ep_release)
    ready = z.socket(zmq.PUSH); ready.setsockopt(zmq.IMMEDIATE, 1); ready.connect(ep_frames)
    cad = Cadence(ring, slabs, ready, rel, z, cfg, resolve_policy(cfg, probe_gpu=False))
    time.sleep(0.3)  # renderer connects, hello arrives
    cad.drain(0)
    period = 1.0 / hz
    times, lates, missed, work = [], [], 0, []
    warm = time.monotonic() + WARMUP_S  # the first handoffs are full 1M-point copies
    if mode == "ticker":
        from pointflow.cadence.ticker import Ticker

        cad.ticker = Ticker(period)
        t_end = time.monotonic() + seconds + WARMUP_S
        while time.monotonic() < t_end:
            tk = cad.ticker.wait(idle=cad.drain, max_wait_s=0.05)
            if tk is None:
                continue
            w0 = time.perf_counter()
            cad.serve(tk)
            work.append(time.perf_counter() - w0)
            if tk.now >= warm:
                times.append(tk.now)
                lates.append(tk.late_s)
                missed += tk.missed
    else:  # naive baseline: relative sleep after the work
        from pointflow.cadence.ticker import Tick

        t_start = time.monotonic()
        t_end = t_start + seconds + WARMUP_S
        k = 0
        while time.monotonic() < t_end:
            time.sleep(period)
            cad.drain(0)
            now = time.monotonic()
            k += 1
            w0 = time.perf_counter()
            cad.serve(Tick(k, t_start + k * period, now, now - (t_start + k * period), 0))
            work.append(time.perf_counter() - w0)
            if now >= warm:
                times.append(now)
                lates.append(now - (t_start + k * period))
    st = cad.stats()
    out.put({"times": times, "lates": lates, "missed": missed, "serve_ms_p50": float(np.median(work)) * 1e3, "published": st["published"],
             "skipped": st["skipped"], "copied_slots": st["copied_slots"]})
    cad.close()
    rel.close(0); ready.close(0); z.term()
    slabs.close(); ring.close()


def run_case(hz: float, load: bool, mode: str, seconds: float, tmp: str) -> dict:
    from pointflow.ring import PointRing, SlabPair

    ctx = mp.get_context("spawn")
    ring = PointRing(RING_POINTS, channels=["intensity"])
    slabs = SlabPair.create(ring.layout)
    ring.push(np.random.default_rng(0).uniform(-50, 50, (RING_POINTS, 3)),
              intensity=np.zeros(RING_POINTS, np.float32))
    ep_f, ep_r = f"ipc://{tmp}/bf.sock", f"ipc://{tmp}/br.sock"
    stop = ctx.Event()
    q = ctx.Queue()
    procs = [ctx.Process(target=null_renderer, args=(tuple(slabs.names), ep_f, ep_r, stop))]
    if load:
        procs.append(ctx.Process(target=loader, args=(ring.name, stop, q)))
    try:
        for p in procs:
            p.start()
        time.sleep(0.5)
        cp = ctx.Process(target=cadence, args=(ring.name, tuple(slabs.names), ep_f, ep_r, hz, mode, seconds, q))
        cp.start()
        res = q.get(timeout=seconds + WARMUP_S + 60)
        cp.join(10)
        stop.set()
        load_res = q.get(timeout=10) if load else {}
        for p in procs:
            p.join(10)
    finally:
        for p in procs:
            if p.is_alive():
                p.kill()
        slabs.close(); slabs.unlink(); ring.close(); ring.unlink()
    t = np.asarray(res["times"])
    late_ms = np.asarray(res["lates"]) * 1e3
    achieved = (t.size - 1) / (t[-1] - t[0]) if t.size > 1 else 0.0
    # jitter is meaningful against absolute deadlines; for the baseline also report period error
    dt_ms = np.diff(t) * 1e3
    return {
        "hz": hz, "load": "ingest" if load else "idle", "mode": mode, "ticks": int(t.size),
        "achieved_hz": round(achieved, 3), "rate_error_pct": round(100 * (achieved - hz) / hz, 3),
        "jitter_ms": {"p50": round(float(np.percentile(late_ms, 50)), 3),
                      "p99": round(float(np.percentile(late_ms, 99)), 3), "max": round(float(late_ms.max()), 3)},
        "period_error_ms_p99": round(float(np.percentile(np.abs(dt_ms - 1e3 / hz), 99)), 3),
        "serve_ms_p50": round(res["serve_ms_p50"], 3),
        "missed": res["missed"], "published": res["published"], "skipped": res["skipped"],
        "ingest_points_per_s": round(load_res.get("points_per_s", 0.0)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--rates", default="30,60,120")
    ap.add_argument("--out", default=str(H.RESULTS / "cadence.json"))
    args = ap.parse_args()
    tmp = os.environ["XDG_RUNTIME_DIR"]
    machine = H.machine()
    rows = []
    for load in (False, True):
        for hz in [float(x) for x in args.rates.split(",")]:
            for mode in ("ticker", "naive"):
                r = run_case(hz, load, mode, args.seconds, tmp)
                rows.append(r)
                print(f"  {r['load']:<6} {hz:5.0f} Hz {mode:<6} achieved {r['achieved_hz']:8.3f} Hz "
                      f"({r['rate_error_pct']:+.2f} %)  jitter p50/p99/max {r['jitter_ms']['p50']:.3f}/"
                      f"{r['jitter_ms']['p99']:.3f}/{r['jitter_ms']['max']:.3f} ms", flush=True)
    print()
    hdr = (f"{'load':<7}{'Hz':>5}  {'achieved':>9} {'err %':>7} {'jit p50':>8} {'jit p99':>8} {'jit max':>8}"
           f" {'skipped':>8} {'tick ms':>8} | {'naive Hz':>9} {'err %':>7} | {'|err| ratio':>11}")
    print(hdr)
    print("-" * len(hdr))
    for t, n in zip(rows[0::2], rows[1::2]):
        ratio = abs(n["rate_error_pct"]) / max(abs(t["rate_error_pct"]), 0.01)
        t["baseline_rate_error_ratio"] = round(ratio, 1)
        sk = sum(t["skipped"].values()) + t["missed"]
        print(f"{t['load']:<7}{t['hz']:>5.0f}  {t['achieved_hz']:>9.3f} {t['rate_error_pct']:>+7.2f} "
              f"{t['jitter_ms']['p50']:>8.3f} {t['jitter_ms']['p99']:>8.3f} {t['jitter_ms']['max']:>8.3f}"
              f" {sk:>8} {t['serve_ms_p50']:>8.2f} | {n['achieved_hz']:>9.3f} {n['rate_error_pct']:>+7.2f} | {ratio:>10.1f}x")
    print("(jitter = lateness after the absolute deadline; naive = sleep(period) then publish; "
          "ratio = naive |rate error| / max(ticker |rate error|, 0.01 %); "
          "tick ms = median work per tick: snapshot copy + handoff)")
    loads = [r["ingest_points_per_s"] for r in rows if r["load"] == "ingest"]
    if loads:
        print(f"ingest load: median {np.median(loads) / 1e6:.1f} M points/s pushed into the ring")
    H.write_result(args.out, {
        "benchmark": "cadence", "seconds_per_case": args.seconds, "ring_points": RING_POINTS, "chunk": CHUNK,
        "machine": H.machine_done(machine), "command": H.command(), "rows": rows}, indent=1)


if __name__ == "__main__":
    main()
