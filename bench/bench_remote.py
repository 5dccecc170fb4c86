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

``--zenoh`` runs the Zenoh engine's pass instead (docs/remote.md, "The Zenoh engine") on
three namespaces, sensor - middle - viewer, joined by two veths, the middle one forwarding
IP packets, so every mode crosses the same two links:

* ``plain``: the ZeroMQ link as above (the baseline of this pass);
* ``zenoh``: :class:`pointflow.remote.zenoh_sender.ZenohLinkSender` (peer, congestion control
  block) to the ``zenoh`` transport (peer, ``backpressure: true``), so the slowest part sets
  the pace without loss, as TCP backpressure does for ZeroMQ's PUSH/PULL; the packets
  forwarded by the middle namespace's kernel;
* ``zenoh+router``: both ends clients of a Zenoh router (a Python ``zenoh`` session in router
  mode) in the middle namespace.

Then the fan-out: N chunks to 4 viewers, ZeroMQ PUB (the viewers subscribe to the sensor)
against Zenoh through the router, counting the bytes leaving the sensor's veth
(``/sys/class/net/DEV/statistics/tx_bytes``). Zenoh's shared memory is off in this pass
(the namespaces share /dev/shm, hosts do not). Writes ``bench/results/remote_zenoh.json``
and ``remote_zenoh.png``::

    sudo .venv/bin/python bench/bench_remote.py --zenoh --dataset ouster [--rounds 3] [--seconds 3]
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

import _harness as H

DATA = str(H.DATA)
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
    from pointflow.stage.context import StageCounters
    import logging

    chunks = load(args.dataset)
    if args.mode.startswith("zenoh") or args.mode == "fanout-zenoh":
        return zenoh_send(args, chunks)
    if args.mode == "fanout-zmq":
        return fanout_zmq_send(args, chunks)
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


def _receive_all(t) -> tuple[int, float | None, float]:
    """Open a receiving transport, say ``ready``, take chunks until the sender's ledger says
    it ended: (points, time of the first chunk, time of the end)."""
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
    return n, t0, time.perf_counter()


def role_recv(args) -> None:
    import zmq

    result = {}
    if args.mode.startswith(("zenoh", "fanout")):
        return zenoh_or_fanout_recv(args)
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
        n, t0, t1 = _receive_all(t)
        t._poll_monitor()
        result = {"points": n, "seconds": t1 - t0, "lost": t.counters.get("lost_in_transit", 0)}
        t.close()
    print(json.dumps(result), flush=True)



# --------------------------------------------------------------------------- zenoh engine
ZPORT = 47447


def _zopts(args, **kw):
    from pointflow.remote.zenoh_options import ZenohOptions

    return ZenohOptions(insecure=True, config_file=args.zconf, **kw)


def zenoh_send(args, chunks) -> None:
    """ZenohLinkSender flat out (congestion control block: the receiver sets the pace), or
    exactly ``--count`` chunks for the fan-out."""
    import logging

    from pointflow.remote.options import SendConfig, check_send
    from pointflow.remote.zenoh_sender import CLOSE_SETTLE_S, ZenohLinkSender, _matching, open_sender_session
    from pointflow.stage.context import StageCounters

    client = "router" in args.mode or "fanout" in args.mode
    z = _zopts(args, mode="client" if client else "peer", connect=[args.endpoint])
    s = SendConfig(engine="zenoh", key="bench", backpressure=True, queue_chunks=4, zenoh=z)
    check_send(s, "send", ".")
    session = open_sender_session(s.zenoh)
    counters = StageCounters()
    snd = ZenohLinkSender(session, s, counters, logging.getLogger("bench"))
    pub = snd._publisher(chunks[0].source_id)
    end = time.monotonic() + 20
    while not _matching(pub) and time.monotonic() < end:
        time.sleep(0.01)
    time.sleep(0.5)  # the fan-out's viewers: every subscription at the router
    deadline = time.monotonic() + args.seconds
    i = 0
    while (i < args.count) if args.count else (time.monotonic() < deadline):
        snd.add(chunks[i % len(chunks)])
        i += 1
        snd.pump()
    snd.sync(end=True)
    snd.pump()
    time.sleep(CLOSE_SETTLE_S)
    snd.close()
    session.close()
    assert not counters.drops, counters.drops
    print(json.dumps({"sent_points": counters.points_out, "bytes": snd.bytes_out}), flush=True)


def fanout_zmq_send(args, chunks) -> None:
    """The ZeroMQ fan-out baseline: LinkSender on a PUB (XPUB) socket that the viewers
    subscribe to; waits for ``--viewers`` subscriptions, sends ``--count`` chunks, no drops
    (a high-water mark above the count)."""
    import logging

    import zmq

    from pointflow.remote.options import SendConfig
    from pointflow.remote.sender import LinkSender
    from pointflow.stage.context import StageCounters

    ctx = zmq.Context()
    sock = ctx.socket(zmq.XPUB)
    sock.setsockopt(zmq.SNDHWM, args.count + 100)
    sock.setsockopt(zmq.LINGER, 10000)
    sock.bind(args.endpoint)
    got = 0
    end = time.monotonic() + 30
    while got < args.viewers and time.monotonic() < end:
        if sock.poll(100, zmq.POLLIN):
            msg = sock.recv()
            got += bool(msg) and msg[0] == 1
    s = SendConfig(endpoint=args.endpoint, socket="pub", insecure=True, queue_chunks=args.count + 10)
    counters = StageCounters()
    snd = LinkSender(sock, s, counters, logging.getLogger("bench"))
    for i in range(args.count):
        snd.add(chunks[i % len(chunks)])
        while not snd.pump():
            sock.poll(5, zmq.POLLOUT)
    snd.sync(end=True)
    while not snd.pump():
        sock.poll(5, zmq.POLLOUT)
    sock.close()  # lingers until ZeroMQ handed every message to TCP
    ctx.term()
    assert not counters.drops, counters.drops
    print(json.dumps({"sent_points": counters.points_out, "bytes": snd.bytes_out, "subscribers": got}), flush=True)


def zenoh_or_fanout_recv(args) -> None:
    """The ``zenoh`` transport (or, for fanout-zmq, the ``zmq`` transport subscribing), until
    the sender's final sync."""
    if args.mode == "fanout-zmq":
        from pointflow.ingest.transports.zmq_transport import ZmqTransport as T

        opts = {"endpoint": args.endpoint, "socket": "sub", "insecure": True, "heartbeat_ivl_s": 0.0,
                "receive_hwm": 100000}
    else:
        from pointflow.ingest.transports.zenoh_transport import ZenohTransport as T

        client = "router" in args.mode or "fanout" in args.mode
        z = {"mode": "client" if client else "peer", "insecure": True, "config_file": args.zconf,
             **({"connect": [args.endpoint]} if client else {"listen": [args.endpoint]})}
        # backpressure: Zenoh's receiving thread waits for the decoder, as ZeroMQ's PULL
        # socket does, so every mode here is lossless and paced by its slowest part
        opts = {"key": "bench/**", "zenoh": z, "queue_chunks": 64, "backpressure": True}
    t = T(T.validate_options(opts, "bench", "."), "bench")
    n, t0, t1 = _receive_all(t)
    result = {"points": n, "seconds": (t1 - t0) if t0 else float("nan"), "lost": t.counters.get("lost_in_transit", 0),
              "receive_queue_full": t.counters.get("receive_queue_full", 0), "link_sent": t.counters.get("link_sent", 0)}
    t.close()
    print(json.dumps(result), flush=True)


def role_router(args) -> None:
    """A Zenoh router: a Python ``zenoh`` session in router mode, until stdin closes."""
    from pointflow.remote.zenoh_options import open_session

    session = open_session(_zopts(args, mode="router", listen=[args.endpoint]))
    print("ready", flush=True)
    sys.stdin.read()
    session.close()


class Hop:
    """sensor - middle - viewer: two veths, the middle namespace forwards IP packets."""

    SENSOR, MID_A, MID_B, VIEWER = "10.233.1.1", "10.233.1.254", "10.233.2.254", "10.233.2.1"

    def __init__(self) -> None:
        tag = secrets.token_hex(3)
        self.tx, self.mid, self.rx = f"pfz-{tag}-tx", f"pfz-{tag}-mid", f"pfz-{tag}-rx"  # not pf-: the tests sweep idle pf-*
        for ns in (self.tx, self.mid, self.rx):
            sh("ip", "netns", "add", ns)
            sh("ip", "-n", ns, "link", "set", "lo", "up")
        self.tx_dev = f"pf{tag}t"
        for a, b, da, db, ipa, ipb in ((self.tx, self.mid, self.tx_dev, f"pf{tag}m", self.SENSOR, self.MID_A),
                                       (self.rx, self.mid, f"pf{tag}r", f"pf{tag}n", self.VIEWER, self.MID_B)):
            sh("ip", "link", "add", da, "type", "veth", "peer", "name", db)
            sh("ip", "link", "set", da, "netns", a)
            sh("ip", "link", "set", db, "netns", b)
            sh("ip", "-n", a, "addr", "add", f"{ipa}/24", "dev", da)
            sh("ip", "-n", b, "addr", "add", f"{ipb}/24", "dev", db)
            sh("ip", "-n", a, "link", "set", da, "up")
            sh("ip", "-n", b, "link", "set", db, "up")
            sh("ip", "-n", a, "route", "add", "default", "via", ipb)
        sh("ip", "netns", "exec", self.mid, "sysctl", "-qw", "net.ipv4.ip_forward=1")

    def tx_bytes(self) -> int:
        out = subprocess.run(["ip", "netns", "exec", self.tx, "cat", f"/sys/class/net/{self.tx_dev}/statistics/tx_bytes"],
                             capture_output=True, text=True, check=True)
        return int(out.stdout)

    def close(self) -> None:
        for ns in (self.tx, self.mid, self.rx):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def _spawn(ns: str, argv: list[str], stdin=None) -> subprocess.Popen:
    return subprocess.Popen(["ip", "netns", "exec", ns, sys.executable, *argv], stdout=subprocess.PIPE,
                            stdin=stdin, text=True)


def _ready(p: subprocess.Popen, what: str) -> None:
    line = p.stdout.readline().strip()
    if line != "ready":
        raise RuntimeError(f"{what} did not start: {line!r}")


def zenoh_one(hop: Hop, mode: str, dataset: str, seconds: float, zconf: str, viewers: int = 1, count: int = 0) -> dict:
    """One run of ``mode`` on the three namespaces; for fan-out modes also the sensor's tx bytes."""
    common = [__file__, "--mode", mode, "--dataset", dataset, "--seconds", str(seconds), "--zconf", zconf,
              "--count", str(count), "--viewers", str(viewers)]
    procs: list[subprocess.Popen] = []
    router = None
    try:
        if mode in ("zenoh+router", "fanout-zenoh"):
            router = _spawn(hop.mid, [*common, "--role", "router", "--endpoint", f"tcp/0.0.0.0:{ZPORT}"],
                            stdin=subprocess.PIPE)
            _ready(router, "router")
            rx_ep, tx_ep = f"tcp/{hop.MID_B}:{ZPORT}", f"tcp/{hop.MID_A}:{ZPORT}"
        elif mode == "zenoh":
            rx_ep = tx_ep = f"tcp/{hop.VIEWER}:{ZPORT}"
        elif mode == "fanout-zmq":
            rx_ep = tx_ep = f"tcp://{hop.SENSOR}:{PORT}"
        else:  # plain ZeroMQ
            rx_ep, tx_ep = f"tcp://0.0.0.0:{PORT}", f"tcp://{hop.VIEWER}:{PORT}"
        if mode == "fanout-zmq":  # the sensor binds; viewers connect
            before = hop.tx_bytes()
            tx = _spawn(hop.tx, [*common, "--role", "send", "--endpoint", tx_ep])
            procs.append(tx)
            time.sleep(1.0)
        for _ in range(viewers):
            rx = _spawn(hop.rx, [*common, "--role", "recv", "--endpoint", rx_ep])
            procs.append(rx)
            _ready(rx, "receiver")
        if mode != "fanout-zmq":
            before = hop.tx_bytes()
            tx = _spawn(hop.tx, [*common, "--role", "send", "--endpoint", tx_ep])
            procs.append(tx)
        out, _ = tx.communicate(timeout=seconds + 180)
        if tx.returncode:
            raise RuntimeError(f"sender failed ({mode})")
        sent = json.loads(out.strip().splitlines()[-1])
        gots = []
        for rx in procs[1:] if mode == "fanout-zmq" else procs[:-1]:
            o, _ = rx.communicate(timeout=120)
            gots.append(json.loads(o.strip().splitlines()[-1]))
        wire_bytes = hop.tx_bytes() - before
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
        if router is not None:
            router.stdin.close()
            try:
                router.wait(10)
            except subprocess.TimeoutExpired:
                router.kill()
                router.wait()
    g = gots[0]
    return {"points_per_s": g["points"] / g["seconds"], "bytes_per_point": sent["bytes"] / max(1, sent["sent_points"]),
            "points": g["points"], "sent": sent["sent_points"], "lost": sum(x.get("lost", 0) for x in gots),
            "receive_queue_full": sum(x.get("receive_queue_full", 0) for x in gots),
            "viewer_points": [x["points"] for x in gots], "payload_bytes": sent["bytes"], "wire_bytes": wire_bytes}


def zenoh_pass(args) -> int:
    import tempfile

    zconf_dir = tempfile.mkdtemp(prefix="pf-bench-zenoh-")
    zconf = os.path.join(zconf_dir, "zenoh.json5")
    with open(zconf, "w") as f:  # the namespaces share /dev/shm; hosts do not
        f.write('{transport: {shared_memory: {enabled: false}}}\n')
    datasets = [args.dataset] if args.dataset != "both" else ["demo", "ouster"]
    modes = ["plain", "zenoh", "zenoh+router"]
    hop = Hop()
    runs: dict = {d: {m: [] for m in modes} for d in datasets}
    fan: dict = {"fanout-zmq": [], "fanout-zenoh": []}
    machine = H.machine()
    try:
        for r in range(args.rounds):
            for d in datasets:
                for m in modes:
                    res = zenoh_one(hop, m, d, args.seconds, zconf)
                    runs[d][m].append(res)
                    print(f"round {r + 1} {d:7s} {m:14s} {res['points_per_s'] / 1e6:7.2f} Mpts/s "
                          f"{res['bytes_per_point']:6.2f} B/pt lost {res['lost']} queue_full {res['receive_queue_full']} "
                          f"load {os.getloadavg()[0]:.1f}", file=sys.stderr, flush=True)
            for m in fan:
                res = zenoh_one(hop, m, datasets[-1], args.seconds, zconf, viewers=4, count=args.fanout_chunks)
                fan[m].append(res)
                print(f"round {r + 1} fan-out {m:13s} payload {res['payload_bytes'] / 1e6:7.1f} MB, sensor veth "
                      f"{res['wire_bytes'] / 1e6:7.1f} MB ({res['wire_bytes'] / res['payload_bytes']:.2f}x), viewers got "
                      f"{res['viewer_points']} of {res['sent']}", file=sys.stderr, flush=True)
    finally:
        hop.close()
        import shutil

        shutil.rmtree(zconf_dir, ignore_errors=True)
    summary: dict = {d: {} for d in datasets}
    for d in datasets:
        for m in modes:
            rs = runs[d][m]
            base = runs[d]["plain"]
            summary[d][m] = {"points_per_s_median": statistics.median(x["points_per_s"] for x in rs),
                             "bytes_per_point": statistics.median(x["bytes_per_point"] for x in rs),
                             "throughput_vs_plain_median": statistics.median(x["points_per_s"] / p["points_per_s"]
                                                                             for x, p in zip(rs, base)),
                             "lost_in_transit": sum(x["lost"] for x in rs),
                             "receive_queue_full": sum(x["receive_queue_full"] for x in rs)}
        summary[d]["zenoh+router"]["throughput_vs_zenoh_median"] = statistics.median(
            x["points_per_s"] / p["points_per_s"] for x, p in zip(runs[d]["zenoh+router"], runs[d]["zenoh"]))
    fsum = {m: {"wire_bytes_over_payload_median": statistics.median(x["wire_bytes"] / x["payload_bytes"] for x in rs),
                "payload_bytes": statistics.median(x["payload_bytes"] for x in rs),
                "wire_bytes_median": statistics.median(x["wire_bytes"] for x in rs),
                "every_viewer_got_everything": all(v == x["sent"] for x in rs for v in x["viewer_points"])}
            for m, rs in fan.items()}
    print(f"\n{'data':7s} {'mode':14s} {'Mpts/s':>8s} {'MB/s':>7s} {'vs zmq':>7s} {'B/point':>8s}")
    for d in datasets:
        for m, x in summary[d].items():
            print(f"{d:7s} {m:14s} {x['points_per_s_median'] / 1e6:8.2f} "
                  f"{x['points_per_s_median'] * x['bytes_per_point'] / 1e6:7.1f} {x['throughput_vs_plain_median']:7.2f} "
                  f"{x['bytes_per_point']:8.2f}" + (f"   router/direct {x['throughput_vs_zenoh_median']:.2f}"
                                                   if "throughput_vs_zenoh_median" in x else ""))
    for m, x in fsum.items():
        print(f"fan-out to 4 viewers, {m:13s}: the sensor's link carried {x['wire_bytes_over_payload_median']:.2f}x "
              f"the payload; every viewer got every point: {x['every_viewer_got_everything']}")
    out = {"chunk_points": CHUNK, "seconds_per_run": args.seconds, "rounds": args.rounds,
           "fanout_chunks": args.fanout_chunks, "machine": H.machine_done(machine), "command": H.command(),
           "summary": summary, "fanout": fsum, "runs": runs, "fanout_runs": fan}
    H.write_result(H.RESULTS / "remote_zenoh.json", out)
    zenoh_chart(out, str(H.RESULTS / "remote_zenoh.png"))
    return 0


def zenoh_chart(out: dict, path: str) -> None:
    """Paired ratios per round against the issue's targets, absolute medians beside the
    ZeroMQ baseline, and the fan-out's bytes on the sensor's link."""
    if (plt := H.pyplot()) is None:
        return
    d = list(out["summary"])[-1]
    runs = out["runs"][d]
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2))
    ax = axes[0]
    pairs = [("Zenoh direct / ZeroMQ", "zenoh", "plain", 0.9), ("via router / direct", "zenoh+router", "zenoh", 0.7)]
    for i, (label, a, b, target) in enumerate(pairs):
        ratios = [x["points_per_s"] / y["points_per_s"] for x, y in zip(runs[a], runs[b])]
        ax.bar(i, statistics.median(ratios), color=["tab:blue", "tab:cyan"][i], alpha=0.7)
        ax.plot([i] * len(ratios), ratios, "k.", ms=6)
        ax.hlines(target, i - 0.4, i + 0.4, colors="tab:red", linestyles="--")
        ax.annotate(f"median {statistics.median(ratios):.2f}\ntarget {target}", (i, statistics.median(ratios)),
                    ha="center", va="bottom", fontsize=8)
    ax.set_xticks([0, 1], [p[0] for p in pairs], fontsize=8)
    ax.set_ylabel("throughput ratio, same round (dots: rounds)")
    ax.set_title(f"{d}: paired ratios")
    ax = axes[1]
    ms = out["summary"][d]
    names = list(ms)
    ax.bar(names, [ms[m]["points_per_s_median"] / 1e6 for m in names], color=["tab:gray", "tab:blue", "tab:cyan"])
    ax.set_ylabel("Mpoints/s delivered (median)")
    ax.set_title(f"{d}: sensor -> middle -> viewer, lossless")
    ax.tick_params(axis="x", labelsize=8)
    ax = axes[2]
    fan = out["fanout"]
    ax.bar(["ZeroMQ PUB", "Zenoh via router"], [fan[m]["wire_bytes_over_payload_median"] for m in fan],
           color=["tab:gray", "tab:blue"])
    ax.axhline(1.0, color="k", lw=0.8, ls=":")
    ax.set_title("fan-out to 4 viewers")
    ax.set_ylabel("bytes on the sensor's veth / payload")
    fig.suptitle(f"Zenoh engine vs ZeroMQ, {CHUNK // 1000}k-point chunks, three network namespaces, {out['rounds']} "
                 f"interleaved rounds ({H.machine_line(out['machine'])})",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


# --------------------------------------------------------------------------- chart
def chart(out: dict, path: str) -> None:
    """Throughput and bytes/point per mode, one panel per link and data set."""
    if (plt := H.pyplot()) is None:
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
    ap.add_argument("--role", choices=["send", "recv", "router"])
    ap.add_argument("--mode", default="plain")
    ap.add_argument("--dataset", default="demo")
    ap.add_argument("--endpoint", default="")
    ap.add_argument("--keys", default="")
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--modes", default=",".join(MODES))
    ap.add_argument("--chart-only", action="store_true", help="redraw the chart from bench/results/remote.json")
    ap.add_argument("--rate", default="1gbit", help="also run on a link shaped to this rate (tc tbf); '' = skip")
    ap.add_argument("--zenoh", action="store_true", help="the Zenoh engine's pass (three namespaces, router, fan-out)")
    ap.add_argument("--zconf", default="", help=argparse.SUPPRESS)
    ap.add_argument("--count", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--viewers", type=int, default=1, help=argparse.SUPPRESS)
    ap.add_argument("--fanout-chunks", type=int, default=300, help="chunks sent in each fan-out run (--zenoh)")
    args = ap.parse_args()
    if args.role == "router":
        role_router(args)
        return 0
    if args.role == "send":
        role_send(args)
        return 0
    if args.role == "recv":
        role_recv(args)
        return 0
    if args.chart_only and args.zenoh:
        with open(H.RESULTS / "remote_zenoh.json") as f:
            zenoh_chart(json.load(f), str(H.RESULTS / "remote_zenoh.png"))
        return 0
    if args.chart_only:
        with open(H.RESULTS / "remote.json") as f:
            chart(json.load(f), str(H.RESULTS / "remote.png"))
        return 0
    if os.geteuid() != 0 or not subprocess.run(["sh", "-c", "command -v ip"], capture_output=True).returncode == 0:
        print("bench_remote needs root and iproute2 (ip netns); skipped", file=sys.stderr)
        return 1
    if args.zenoh:
        return zenoh_pass(args)
    import tempfile

    from pointflow.remote.keys import create_keypair

    machine = H.machine()

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
           "machine": H.machine_done(machine), "command": H.command(), "summary": summary, "runs": runs}
    H.write_result(H.RESULTS / "remote.json", out)
    chart(out, str(H.RESULTS / "remote.png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
