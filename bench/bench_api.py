"""Pipeline.send throughput (issue 28): clouds from the caller's Python code into the ring.

Same run, same pipeline, interleaved, medians of ``--repeats``; for clouds of 1k, 10k and
100k points (float32 xyz + float32 intensity), points/s from the first send until the ring's
own write counter (in shared memory) shows the last point stored:

* ``send``: ``Pipeline.send`` (the in-process ``api`` source -> ingest);
* ``wire``: the documented way before it, ``pointflow.wire.send`` on a PUSH socket to a
  ``zmq`` source (a source process) -> ingest;
* ``rerun``: rerun-sdk's ``rr.log("points", rr.Points3D(xyz), rr.AnyValues(intensity=...))``
  into a memory sink (``rr.memory_recording()``), timed until the recording is drained. It is
  installed by this benchmark when missing (``pip install rerun-sdk``); not a dependency.

Targets: send >= 0.8 x wire, send >= 2 x rerun, at every size.

``--handoff`` also measures, between two processes, the two ways to hand a large cloud to the
stage that writes the ring: ZeroMQ over ipc (``copy=False``: no copy in the sender;
``copy=True``: one copy, what ``send`` does so the caller may reuse its arrays at once)
against a shared-memory staging area (the sender copies the cloud into a slot, sends a
descriptor, the receiver copies from the slot and releases it). The receiver copies every
cloud into a destination array in each case, as ingest writes the ring.

    .venv/bin/python bench/bench_api.py [--repeats 5] [--points 2000000] [--handoff]

Writes ``bench/results/api.json``.
"""
from __future__ import annotations

import argparse
import importlib
import multiprocessing as mp
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np
import zmq

import _harness as H

SIZES = (1_000, 10_000, 100_000)


def _rerun():
    """rerun-sdk, installed into this interpreter when missing (the benchmark's set-up)."""
    try:
        return importlib.import_module("rerun")
    except ImportError:
        subprocess.run([sys.executable, "-m", "pip", "install", "-q", "rerun-sdk"], check=True)
        importlib.invalidate_caches()
        return importlib.import_module("rerun")


def _clouds(n: int, k: int):
    rng = np.random.default_rng(n)
    base = [(rng.uniform(-50, 50, (n, 3)).astype(np.float32), rng.uniform(0, 255, n).astype(np.float32))
            for _ in range(min(k, 8))]
    return [base[i % len(base)] for i in range(k)]


def _wait_written(p, target: int, timeout_s: float = 300.0) -> float:
    """Until the ring's own write counter reaches ``target``, less what the sources dropped
    on the way (a live ``zmq`` source drops when ingest stays behind for 100 ms: counted, and
    seen here a heartbeat later; the run is then marked in ``dropped``)."""
    ring = p.supervisor.ring
    end = time.monotonic() + timeout_s
    look = time.monotonic() + 0.5
    while True:
        if ring.stats().total_written >= target:
            return time.perf_counter()
        now = time.monotonic()
        if now > end:
            raise TimeoutError(f"ring wrote {ring.stats().total_written} of {target} points")
        if now > look:  # stats() is not free: drops are looked at twice a second
            look = now + 0.5
            d = _dropped(p) - _DROPPED_AT_START[0]
            if d and ring.stats().total_written + d >= target:
                return time.perf_counter()
        time.sleep(0.001)


_DROPPED_AT_START = [0]
DROPS: list = []


def _dropped(p) -> int:
    st = p.stats()["stages"]
    return sum(sum(st[s].get("drops", {}).values()) for s in ("api", "zmqsrc") if s in st)


def _mark(p) -> None:
    _DROPPED_AT_START[0] = _dropped(p)


def _note_drops(p, name: str, n: int) -> None:
    d = _dropped(p) - _DROPPED_AT_START[0]
    if d:
        DROPS.append({"path": name, "cloud_points": n, "dropped": d})


def run_send(p, clouds) -> float:
    ring = p.supervisor.ring
    total = sum(len(c[0]) for c in clouds)
    start = ring.stats().total_written
    _mark(p)
    t0 = time.perf_counter()
    for pos, inten in clouds:
        p.send(pos, intensity=inten)
    t1 = _wait_written(p, start + total)
    _note_drops(p, "send", len(clouds[0][0]))
    return total / (t1 - t0)


def run_wire(p, sock, clouds) -> float:
    from pointflow import wire
    from pointflow.chunk import PointChunk

    ring = p.supervisor.ring
    total = sum(len(c[0]) for c in clouds)
    start = ring.stats().total_written
    _mark(p)
    t0 = time.perf_counter()
    for i, (pos, inten) in enumerate(clouds):
        wire.send(sock, PointChunk(pos, {"intensity": inten}, "ext", i))
    t1 = _wait_written(p, start + total)
    _note_drops(p, "wire", len(clouds[0][0]))
    return total / (t1 - t0)


def run_rerun(rr, clouds) -> float:
    rr.init("pointflow-bench", spawn=False)
    rec = rr.memory_recording()
    total = sum(len(c[0]) for c in clouds)
    t0 = time.perf_counter()
    for i, (pos, inten) in enumerate(clouds):
        rr.set_time("frame", sequence=i)
        rr.log("points", rr.Points3D(pos), rr.AnyValues(intensity=inten))
    nbytes = len(rec.drain_as_bytes())  # waits until everything logged is in the sink
    t1 = time.perf_counter()
    assert nbytes > total * 12
    return total / (t1 - t0)


def pipeline_bench(repeats: int, points: int, sizes) -> dict:
    from pointflow import Pipeline

    rr = _rerun()
    tmp = tempfile.mkdtemp(prefix="pf-bench-api-")
    ep = f"ipc://{tmp}/zmq-source.sock"
    cfg = {
        "name": "bench-api",
        "sources": [{"transport": "api", "name": "api"},
                    {"transport": "zmq", "name": "zmqsrc", "options": {"endpoint": ep, "socket": "pull", "bind": True}}],
        "ring": {"max_points": 1_000_000},
        "cadence": {"target_hz": 2},
        "render": {"backend": "cpu", "size": [64, 48], "color_by": "intensity", "output": {"dir": None}},
        "tracing": {"enabled": False},
        "supervisor": {"standby": False},
    }
    p = Pipeline.from_dict(cfg, out_dir="")
    p.start()
    ctx = zmq.Context()
    sock = ctx.socket(zmq.PUSH)
    sock.setsockopt(zmq.SNDHWM, 64)
    sock.connect(ep)
    out: dict = {}
    try:
        warm = _clouds(1000, 50)
        run_send(p, warm)
        run_wire(p, sock, warm)
        for n in sizes:
            k = max(4, (points if n < 100_000 else 3 * points) // n)
            clouds = _clouds(n, k)
            res = {"send": [], "wire": [], "rerun": []}
            for r in range(repeats):
                order = H.order(["send", "wire", "rerun"], r)
                for name in order:
                    if name == "send":
                        res[name].append(run_send(p, clouds))
                    elif name == "wire":
                        res[name].append(run_wire(p, sock, clouds))
                    else:
                        res[name].append(run_rerun(rr, clouds))
            med = {k2: statistics.median(v) for k2, v in res.items()}
            # each repeat's runs are adjacent in time: the median of the per-repeat ratios is
            # the figure least moved by the machine's load swinging between repeats
            pair_w = [a / b for a, b in zip(res["send"], res["wire"])]
            pair_r = [a / b for a, b in zip(res["send"], res["rerun"])]
            out[str(n)] = {"clouds": k, "points_per_s": res, "median": med,
                           "send_over_wire": statistics.median(pair_w), "send_over_rerun": statistics.median(pair_r),
                           "send_over_wire_per_repeat": pair_w, "send_over_rerun_per_repeat": pair_r,
                           "ratio_of_medians": {"wire": med["send"] / med["wire"], "rerun": med["send"] / med["rerun"]}}
            print(f"{n:>7} pts x {k:>5}: send {med['send'] / 1e6:7.1f} M/s  wire {med['wire'] / 1e6:7.1f} M/s  "
                  f"rerun {med['rerun'] / 1e6:7.1f} M/s   send/wire {out[str(n)]['send_over_wire']:.2f} (>= 0.8)  "
                  f"send/rerun {out[str(n)]['send_over_rerun']:.2f} (>= 2)", flush=True)
        stats = p.stats()
        out["accounting"] = {k2: stats["accounting"].get(k2) for k2 in
                             ("sources_balanced", "ingest_balanced", "ring_agrees", "ingest_dropped")}
        out["rerun_version"] = rr.__version__
        out["runs_with_drops"] = DROPS
    finally:
        sock.close(0)
        ctx.term()
        p.stop()
    return out


# ----------------------------------------------------------------------------- handoff
def _receiver(kind: str, ep: str, back: str, n: int, k: int, shm_name: str, q) -> None:
    ctx = zmq.Context()
    pull = ctx.socket(zmq.PULL)
    pull.bind(ep)
    dst_pos = np.empty((n, 3), np.float32)
    dst_int = np.empty(n, np.float32)
    if kind == "shm":
        from multiprocessing import shared_memory

        rel = ctx.socket(zmq.PUSH)
        rel.connect(back)
        shm = shared_memory.SharedMemory(shm_name)
        slot_bytes = n * 16
    q.put("ready")
    for _ in range(k):
        if kind == "shm":
            slot = int.from_bytes(pull.recv(), "little")
            base = slot * slot_bytes
            np.copyto(dst_pos, np.ndarray((n, 3), np.float32, shm.buf, base))
            np.copyto(dst_int, np.ndarray((n,), np.float32, shm.buf, base + n * 12))
            rel.send(slot.to_bytes(4, "little"))
        else:
            f = pull.recv_multipart(copy=False)
            np.copyto(dst_pos, np.frombuffer(f[0].buffer, np.float32).reshape(n, 3))
            np.copyto(dst_int, np.frombuffer(f[1].buffer, np.float32))
    q.put(time.perf_counter())
    if kind == "shm":
        del dst_pos
        shm.close()
        rel.close(0)
    pull.close(0)
    ctx.term()


def handoff(kind: str, n: int, k: int, tmp: str) -> float:
    """Points/s handed from this process to another that copies them out (see module doc)."""
    from multiprocessing import shared_memory

    ep, back = f"ipc://{tmp}/h-{kind}.sock", f"ipc://{tmp}/h-{kind}-back.sock"
    slots = 4
    shm = shared_memory.SharedMemory(create=True, size=slots * n * 16) if kind == "shm" else None
    q = mp.get_context("spawn").Queue()
    proc = mp.get_context("spawn").Process(target=_receiver, args=(kind, ep, back, n, k, shm.name if shm else "", q))
    proc.start()
    ctx = zmq.Context()
    push = ctx.socket(zmq.PUSH)
    push.setsockopt(zmq.SNDHWM, 8)
    push.connect(ep)
    if kind == "shm":
        rel = ctx.socket(zmq.PULL)
        rel.bind(back)
    q.get(timeout=60)
    pos, inten = _clouds(n, 1)[0]
    free = list(range(slots))
    t0 = time.perf_counter()
    for _ in range(k):
        if kind == "shm":
            if not free:
                free.append(int.from_bytes(rel.recv(), "little"))
            s = free.pop()
            base = s * n * 16
            np.copyto(np.ndarray((n, 3), np.float32, shm.buf, base), pos)
            np.copyto(np.ndarray((n,), np.float32, shm.buf, base + n * 12), inten)
            push.send(s.to_bytes(4, "little"))
        else:
            push.send_multipart([memoryview(pos).cast("B"), memoryview(inten).cast("B")], copy=(kind == "zmq_copy"))
    t1 = q.get(timeout=300)
    proc.join(30)
    push.close(0)
    if kind == "shm":
        rel.close(0)
        shm.close()
        shm.unlink()
    ctx.term()
    return n * k / (t1 - t0)


def handoff_bench(repeats: int) -> dict:
    tmp = tempfile.mkdtemp(prefix="pf-bench-handoff-")
    out = {}
    for n, k in ((100_000, 200), (1_000_000, 30)):
        res = {"zmq_zero_copy": [], "zmq_copy": [], "shm": []}
        for r in range(repeats):
            for kind in H.order(["zmq_zero_copy", "zmq_copy", "shm"], r):
                res[kind].append(handoff({"zmq_zero_copy": "zmq", "zmq_copy": "zmq_copy", "shm": "shm"}[kind], n, k, tmp))
        med = {kk: statistics.median(v) for kk, v in res.items()}
        out[str(n)] = {"clouds": k, "points_per_s": res, "median": med}
        print(f"handoff {n:>9} pts: zmq zero-copy {med['zmq_zero_copy'] / 1e6:7.1f} M/s  zmq copy "
              f"{med['zmq_copy'] / 1e6:7.1f} M/s  shm staging {med['shm'] / 1e6:7.1f} M/s", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--points", type=int, default=2_000_000,
                    help="points per run and size (three times that for 100k-point clouds)")
    ap.add_argument("--sizes", default=",".join(map(str, SIZES)))
    ap.add_argument("--handoff", action="store_true")
    ap.add_argument("--out", default=str(H.RESULTS / "api.json"))
    a = ap.parse_args()
    result = {"machine": H.machine(), "command": H.command(), "repeats": a.repeats, "points_per_run": a.points}
    result["pipeline"] = pipeline_bench(a.repeats, a.points, [int(s) for s in a.sizes.split(",")])
    if a.handoff:
        result["handoff"] = handoff_bench(max(3, a.repeats // 2))
    m = H.machine_done(result["machine"])
    print(m["uptime_before"], "->", m["uptime_after"])
    H.write_result(a.out, result)


if __name__ == "__main__":
    main()
