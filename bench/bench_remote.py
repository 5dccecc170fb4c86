"""Link throughput and bytes on the wire between two network namespaces (docs/remote.md).

Two namespaces joined by a veth pair (root and iproute2 needed); a sender process in one,
a receiver process in the other. 10k-point chunks, sent as fast as the link takes them:

* ``raw``: pyzmq PUSH/PULL of the pre-encoded plain wire frames, no per-chunk work (floor);
* ``plain``: the link code (:class:`pointflow.remote.sender.LinkSender`: per-chunk link
  header, encode; :class:`~pointflow.ingest.transports.zmq_transport.ZmqTransport` on the
  receiving end: decode, ledger), no CURVE;
* ``curve``, ``curve+lz4``, ``curve+zstd``, ``curve+q1mm`` (positions quantised to 1 mm),
  ``curve+q1mm+lz4``, ``curve+q1mm+zstd``.

The sender runs flat out, so the slower end sets the pace through TCP backpressure;
ZeroMQ heartbeats are off here because a receiver that falls behind stops reading its
socket, and then also the peer's heartbeats (docs/remote.md, "Limits").

Data: the demo scene (synthetic lidar, float64 xyz + intensity float32 + classification
uint8) and, when ``../shared/data/ouster_os1_128`` exists, the Ouster OS-1-128 scans (float32
xyz + reflectivity uint8). Modes are interleaved, ``--rounds`` times; medians, and ratios
to ``plain`` from the same round.

    sudo .venv/bin/python bench/bench_remote.py [--rounds 3] [--seconds 2] [--rate 1gbit]

A second pass repeats the main modes on the same veth shaped to ``--rate`` (tc tbf), the
case of a real network link, where the wire and not the CPU sets the pace.

Prints a table, writes ``bench/results/remote.json`` and ``remote.png``.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import secrets
import statistics
import subprocess
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
DATA = os.path.join(ROOT, "..", "shared", "data")
CHUNK = 10_000
PORT = 47411
MODES = {
    "raw": {},
    "plain": {},
    "curve": {"curve": True},
    "curve+lz4": {"curve": True, "compression": "lz4"},
    "curve+zstd": {"curve": True, "compression": "zstd"},
    "curve+q1mm": {"curve": True, "quantise": 0.001},
    "curve+q1mm+lz4": {"curve": True, "quantise": 0.001, "compression": "lz4"},
    "curve+q1mm+zstd": {"curve": True, "quantise": 0.001, "compression": "zstd"},
}


# --------------------------------------------------------------------------- data
def demo_chunks(n_chunks: int = 20) -> list:
    from pointflow.ingest.transports.synthetic import SyntheticTransport

    t = SyntheticTransport(SyntheticTransport.validate_options({"points_per_scan": 100_000, "chunks_per_scan": 10,
                                                                "realtime": False, "seed": 3}, "s"), "demo")
    t.open()
    out = []
    for c in t.chunks():
        if c is not None:
            out.append(c)
        if len(out) >= n_chunks:
            break
    t.close()
    return out


def ouster_chunks() -> list:
    from pointflow.chunk import PointChunk

    out = []
    for f in sorted(glob.glob(os.path.join(DATA, "ouster_os1_128", "*.npz"))):
        with np.load(f) as z:
            xyz, refl = z["xyz"].reshape(-1, 3), z["reflectivity"].reshape(-1)
        for i in range(0, len(xyz), CHUNK):
            out.append(PointChunk(positions=np.ascontiguousarray(xyz[i:i + CHUNK]),
                                  channels={"intensity": np.ascontiguousarray(refl[i:i + CHUNK])}, source_id="ouster"))
    return out


def load(dataset: str) -> list:
    return demo_chunks() if dataset == "demo" else ouster_chunks()


# --------------------------------------------------------------------------- roles
def role_send(args) -> None:
    import zmq

    from pointflow import wire
    from pointflow.remote.options import SendConfig
    from pointflow.remote.security import LinkSecurity
    from pointflow.remote.sender import LinkSender
    from pointflow.runtime.stage import StageCounters
    import logging

    chunks = load(args.dataset)
    m = MODES[args.mode]
    ctx = zmq.Context()
    sock = ctx.socket(zmq.PUSH)
    sock.setsockopt(zmq.SNDHWM, 16)
    sock.setsockopt(zmq.LINGER, 3000)
    deadline = time.monotonic() + args.seconds
    n_sent = bytes_out = 0
    if args.mode == "raw":
        frames = [[bytes(f) for f in wire.encode(c)] for c in chunks]
        sock.connect(args.endpoint)
        i = 0
        while time.monotonic() < deadline:
            fr = frames[i % len(frames)]
            sock.send_multipart(fr, copy=False)
            n_sent += chunks[i % len(chunks)].n
            bytes_out += sum(len(f) for f in fr)
            i += 1
        sock.send_multipart([b"END"])
    else:
        s = SendConfig(endpoint=args.endpoint, socket="push", bind=False, compression=m.get("compression", "none"),
                       quantise=m.get("quantise", 0.0), insecure=True, queue_chunks=4, heartbeat_ivl_s=0.0)
        if m.get("curve"):
            s.curve_secret_key, s.curve_server_key = args.keys + "/sensor.key_secret", args.keys + "/viewer.key"
        link = LinkSecurity(ctx, s, False, logging.getLogger("bench"))
        link.apply(sock)
        if s.send_buffer_kb:
            sock.setsockopt(zmq.SNDBUF, s.send_buffer_kb * 1024)
        sock.connect(args.endpoint)
        counters = StageCounters()
        snd = LinkSender(sock, s, counters, logging.getLogger("bench"))
        i = 0
        while time.monotonic() < deadline:
            if len(snd.queue) < s.queue_chunks:
                snd.add(chunks[i % len(chunks)])
                i += 1
            if not snd.pump():
                sock.poll(5, zmq.POLLOUT)
        snd.sync(end=True)
        while snd.queue:
            if not snd.pump():
                sock.poll(5, zmq.POLLOUT)
        n_sent, bytes_out = counters.points_out, snd.bytes_out
        assert not counters.drops, counters.drops
        link.close()
    sock.close()
    ctx.term()
    print(json.dumps({"sent_points": n_sent, "bytes": bytes_out}), flush=True)


def role_recv(args) -> None:
    import zmq

    result = {}
    if args.mode == "raw":
        ctx = zmq.Context()
        sock = ctx.socket(zmq.PULL)
        sock.bind(args.endpoint)
        print("ready", flush=True)
        n = 0
        t0 = None
        while True:
            fr = sock.recv_multipart(copy=False)
            if len(fr) == 1:
                break
            if t0 is None:
                t0 = time.perf_counter()
            n += len(fr[1]) // 12 // (2 if b'"float64"' in fr[0].bytes[:400] else 1)
        result = {"points": n, "seconds": time.perf_counter() - t0}
        sock.close()
        ctx.term()
    else:
        from pointflow.ingest.transports.zmq_transport import ZmqTransport

        m = MODES[args.mode]
        opts = {"endpoint": args.endpoint, "socket": "pull", "bind": True, "insecure": True, "receive_hwm": 64,
                "heartbeat_ivl_s": 0.0}
        if m.get("curve"):
            opts.update(insecure=False, curve_secret_key=args.keys + "/viewer.key_secret",
                        curve_authorized_keys=args.keys + "/clients")
        t = ZmqTransport(ZmqTransport.validate_options(opts, "bench", "."), "bench")
        t.open()
        print("ready", flush=True)
        n, t0 = 0, None
        for c in t.chunks():
            if c is not None:
                if t0 is None:
                    t0 = time.perf_counter()
                n += c.n
            if t.ledger.ended:
                break
        t1 = time.perf_counter()
        t._poll_monitor()
        result = {"points": n, "seconds": t1 - t0, "lost": t.counters.get("lost_in_transit", 0)}
        t.close()
    print(json.dumps(result), flush=True)


# --------------------------------------------------------------------------- chart
def chart(out: dict, path: str) -> None:
    """Throughput and bytes/point per mode, one panel per link and data set."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    panels = [(p, d) for p, ds in out["summary"].items() for d in ds]
    fig, axes = plt.subplots(2, len(panels), figsize=(4.2 * len(panels), 6.5), squeeze=False)
    for i, (p, d) in enumerate(panels):
        ms = out["summary"][p][d]
        names = list(ms)
        axes[0][i].bar(names, [ms[m]["points_per_s_median"] / 1e6 for m in names], color="tab:blue")
        axes[0][i].set_title(f"{d}, {p}")
        axes[0][i].set_ylabel("Mpoints/s (median)")
        axes[1][i].bar(names, [ms[m]["bytes_per_point"] for m in names], color="tab:orange")
        axes[1][i].set_ylabel("bytes/point on the wire")
        for ax in (axes[0][i], axes[1][i]):
            ax.tick_params(axis="x", rotation=60, labelsize=7)
    fig.suptitle("pointflow link, 10k-point chunks between two network namespaces (shared 2-core machine)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


# --------------------------------------------------------------------------- orchestration
def sh(*a: str) -> None:
    subprocess.run(list(a), check=True, capture_output=True)


class Link:
    def __init__(self) -> None:
        tag = secrets.token_hex(3)
        self.a, self.b = f"pf-{tag}-tx", f"pf-{tag}-rx"
        for ns in (self.a, self.b):
            sh("ip", "netns", "add", ns)
            sh("ip", "-n", ns, "link", "set", "lo", "up")
        sh("ip", "link", "add", f"pf{tag}a", "type", "veth", "peer", "name", f"pf{tag}b")
        sh("ip", "link", "set", f"pf{tag}a", "netns", self.a)
        sh("ip", "link", "set", f"pf{tag}b", "netns", self.b)
        sh("ip", "-n", self.a, "addr", "add", "10.232.0.1/24", "dev", f"pf{tag}a")
        sh("ip", "-n", self.b, "addr", "add", "10.232.0.2/24", "dev", f"pf{tag}b")
        sh("ip", "-n", self.a, "link", "set", f"pf{tag}a", "up")
        sh("ip", "-n", self.b, "link", "set", f"pf{tag}b", "up")
        self.tx_dev = f"pf{tag}a"

    def shape(self, rate: str | None) -> None:
        """Limit the sender's side to ``rate`` (tc tbf), or remove the limit."""
        if rate:
            sh("ip", "netns", "exec", self.a, "tc", "qdisc", "replace", "dev", self.tx_dev, "root", "tbf",
               "rate", rate, "burst", "1mb", "latency", "100ms")
        else:
            subprocess.run(["ip", "netns", "exec", self.a, "tc", "qdisc", "del", "dev", self.tx_dev, "root"],
                           capture_output=True)

    def close(self) -> None:
        for ns in (self.a, self.b):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def one(link: Link, mode: str, dataset: str, seconds: float, keys: str) -> dict:
    ep = "tcp://10.232.0.2:%d" % PORT
    common = [__file__, "--mode", mode, "--dataset", dataset, "--endpoint", ep, "--keys", keys,
              "--seconds", str(seconds)]
    rx = subprocess.Popen(["ip", "netns", "exec", link.b, sys.executable, *common, "--role", "recv"],
                          stdout=subprocess.PIPE, text=True)
    try:
        assert rx.stdout.readline().strip() == "ready"
        tx = subprocess.run(["ip", "netns", "exec", link.a, sys.executable, *common, "--role", "send"],
                            capture_output=True, text=True, timeout=seconds + 120)
        if tx.returncode:
            raise RuntimeError(f"sender failed: {tx.stderr[-2000:]}")
        sent = json.loads(tx.stdout.strip().splitlines()[-1])
        out, _ = rx.communicate(timeout=60)
        got = json.loads(out.strip().splitlines()[-1])
    finally:
        if rx.poll() is None:
            rx.kill()
            rx.wait()
    return {"points_per_s": got["points"] / got["seconds"], "bytes_per_point": sent["bytes"] / max(1, sent["sent_points"]),
            "points": got["points"], "sent": sent["sent_points"], "lost": got.get("lost", 0)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--role", choices=["send", "recv"])
    ap.add_argument("--mode", default="plain")
    ap.add_argument("--dataset", default="demo")
    ap.add_argument("--endpoint", default="")
    ap.add_argument("--keys", default="")
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--modes", default=",".join(MODES))
    ap.add_argument("--chart-only", action="store_true", help="redraw the chart from bench/results/remote.json")
    ap.add_argument("--rate", default="1gbit", help="also run on a link shaped to this rate (tc tbf); '' = skip")
    args = ap.parse_args()
    if args.role == "send":
        role_send(args)
        return 0
    if args.role == "recv":
        role_recv(args)
        return 0
    if args.chart_only:
        with open(os.path.join(ROOT, "bench", "results", "remote.json")) as f:
            chart(json.load(f), os.path.join(ROOT, "bench", "results", "remote.png"))
        return 0
    if os.geteuid() != 0 or not subprocess.run(["sh", "-c", "command -v ip"], capture_output=True).returncode == 0:
        print("bench_remote needs root and iproute2 (ip netns); skipped", file=sys.stderr)
        return 1
    import tempfile

    from pointflow.remote.keys import create_keypair

    keys = tempfile.mkdtemp(prefix="pf-bench-keys-")
    create_keypair("viewer", keys)
    create_keypair("sensor", keys)
    os.makedirs(os.path.join(keys, "clients"))
    os.link(os.path.join(keys, "sensor.key"), os.path.join(keys, "clients", "sensor.key"))
    datasets = ["demo"] + (["ouster"] if glob.glob(os.path.join(DATA, "ouster_os1_128", "*.npz")) else [])
    if len(datasets) == 1:
        print("note: ../shared/data/ouster_os1_128 not found; Ouster part skipped", file=sys.stderr)
    modes = args.modes.split(",")
    link = Link()
    passes = [("veth", None, modes)]
    if args.rate:
        passes.append((f"tbf {args.rate}", args.rate, [m for m in ("plain", "curve", "curve+lz4", "curve+q1mm+lz4", "curve+q1mm+zstd") if m in modes]))
    runs: dict = {p: {d: {m: [] for m in ms} for d in datasets} for p, _, ms in passes}
    try:
        for pname, rate, pmodes in passes:
            link.shape(rate)
            for r in range(args.rounds):
                for d in datasets:
                    for m in pmodes:
                        res = one(link, m, d, args.seconds, keys)
                        runs[pname][d][m].append(res)
                        print(f"{pname} round {r + 1} {d:7s} {m:16s} {res['points_per_s'] / 1e6:7.2f} Mpts/s "
                              f"{res['bytes_per_point']:6.2f} B/pt lost {res['lost']}", file=sys.stderr, flush=True)
    finally:
        link.close()
        import shutil

        shutil.rmtree(keys, ignore_errors=True)
    summary: dict = {}
    for pname, _, pmodes in passes:
        summary[pname] = {}
        for d in datasets:
            summary[pname][d] = {}
            for m in pmodes:
                rs = runs[pname][d][m]
                ratios = [x["points_per_s"] / p["points_per_s"] for x, p in zip(rs, runs[pname][d].get("plain", rs))]
                summary[pname][d][m] = {"points_per_s_median": statistics.median(x["points_per_s"] for x in rs),
                                        "bytes_per_point": statistics.median(x["bytes_per_point"] for x in rs),
                                        "throughput_vs_plain_median": statistics.median(ratios),
                                        "lost_in_transit": sum(x["lost"] for x in rs)}
    print(f"\n{'link':14s} {'data':7s} {'mode':16s} {'Mpts/s':>8s} {'MB/s':>7s} {'vs plain':>9s} {'B/point':>8s} {'vs plain':>9s}")
    for pname in summary:
        for d in datasets:
            plain_b = summary[pname][d].get("plain", {}).get("bytes_per_point", float("nan"))
            for m, s in summary[pname][d].items():
                print(f"{pname:14s} {d:7s} {m:16s} {s['points_per_s_median'] / 1e6:8.2f} "
                      f"{s['points_per_s_median'] * s['bytes_per_point'] / 1e6:7.1f} {s['throughput_vs_plain_median']:9.2f} "
                      f"{s['bytes_per_point']:8.2f} {s['bytes_per_point'] / plain_b:9.2f}")
    out = {"chunk_points": CHUNK, "seconds_per_run": args.seconds, "rounds": args.rounds, "rate": args.rate,
           "machine": f"{os.cpu_count()} cores, shared with other jobs", "summary": summary, "runs": runs}
    os.makedirs(os.path.join(ROOT, "bench", "results"), exist_ok=True)
    with open(os.path.join(ROOT, "bench", "results", "remote.json"), "w") as f:
        json.dump(out, f, indent=2)
    chart(out, os.path.join(ROOT, "bench", "results", "remote.png"))
    print("wrote bench/results/remote.json and remote.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
