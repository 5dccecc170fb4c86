"""Zenoh topologies across separate network stacks (docs/remote.md, "Routers and TLS"):
`pointflow send` (engine zenoh, client mode) on sensor hosts, `pointflow router` on a
host of its own, viewers (`pointflow run` with the zenoh source, or the real transport in a
probe process) on others; Linux network namespaces joined by veth pairs, as the ZeroMQ link
tests (netns.py). Run as root; under CI=true they must run.

Zenoh moves large messages through shared memory between processes of one machine
(``transport/shared_memory``), and network namespaces share /dev/shm: every end here gets
a Zenoh config file (the ``config_file`` pass-through) that turns it off, so the points
really cross the veth links, as they cross the network between hosts.

What the product guarantees, and so what these tests assert (on a shared, busy machine:
no timing asserts, generous waits on conditions): with ``backpressure`` on both ends
(a replay) every point of every sensor arrives at every viewer through the router; live
(the default) nothing waits for the network, and every point a viewer does not get is
counted (lost in transit, or dropped by its own queue) in identities that balance.
"""
from __future__ import annotations

import json
import os
import signal
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("zenoh", reason="eclipse-zenoh comes with the remote extra: pip install 'pointflow[remote]'")

from pointflow.remote.tls import make_certificate  # noqa: E402

from .helpers import synthetic_source, wait_for, write_cfg  # noqa: E402
from .netns import REPO, Net, read_stats, stop  # noqa: E402

PORT = 7447


# ----------------------------------------------------------------------------- configs
def tls_block(certs: Path, name: str, ca: Path | None = None) -> dict:
    other = certs.parent / "other-ca"
    d = other if (other / f"{name}.pem").exists() else certs
    return {"root_ca": str((ca or certs) / "ca.pem"), "certificate": str(d / f"{name}.pem"),
            "private_key": str(d / f"{name}-key.pem")}


def net_config(net: Net, extra: str = "", name: str = "zenoh") -> str:
    """A Zenoh config file in the test's folder: no shared memory (separate hosts share
    none), plus ``extra`` (JSON5 members of ``transport.link``)."""
    path = net.workdir / f"{name}.json5"
    path.write_text(f"{{transport: {{shared_memory: {{enabled: false}}, link: {{{extra}}}}}}}")
    return str(path)


def zenoh_client(net: Net, router_addr: str, tls: dict | None = None) -> dict:
    if tls:
        return {"mode": "client", "connect": [f"tls/{router_addr}:{PORT}"], "tls": tls, "config_file": net_config(net)}
    return {"mode": "client", "connect": [f"tcp/{router_addr}:{PORT}"], "insecure": True,
            "config_file": net_config(net)}


#: A stage that fails is not restarted (so nothing is hidden), and one that is silent for a
#: second on a machine at load 10+ is not taken for hung.
SUPERVISOR = {"max_restarts": 0, "hung_after_ms": 10_000}


def send_cfg(source: dict, key: str, zenoh: dict, **send) -> dict:
    return {"sources": [source], "supervisor": SUPERVISOR,
            "send": {"engine": "zenoh", "key": key, "queue_chunks": 256, "wait_subscribers": 1, "wait_s": 60,
                     "zenoh": zenoh, **send}}


def view_cfg(zenoh: dict, **opts) -> dict:
    return {"source": {"transport": "zenoh", "name": "link", "options": {"key": "pf/**", "zenoh": zenoh, **opts}},
            "ring": {"max_points": 300_000},
            "cadence": {"target_hz": 10},
            "render": {"backend": "cpu", "size": [64, 48], "output": {"dir": None}},
            "tracing": {"enabled": False},
            "supervisor": SUPERVISOR}


def start_router(net: Net, ns: str, listen: str, name: str = "router", **router):
    router.setdefault("config_file", net_config(net))
    path = write_cfg(net.workdir / f"{name}.yaml", {"router": {"listen": [listen], "stats_every_s": 1.0, **router},
                                                    "supervisor": {"hung_after_ms": 10_000}})
    p = net.pointflow(ns, "router", path, "--out", str(net.workdir / name), log=f"{name}.log")
    wait_for(lambda: " listening on " in net.log(f"{name}.log"), 60, f"{name} to listen", lambda: net.log(f"{name}.log"))
    return p


def start_view(net: Net, ns: str, cfg: dict, name: str):
    path = write_cfg(net.workdir / f"{name}.yaml", cfg)
    p = net.pointflow(ns, "run", path, "--duration", "300", "--out", str(net.workdir / name), "-q", log=f"{name}.log")
    wait_for(lambda: "subscribed zenoh" in net.log(f"{name}.log"), 60, f"{name} to subscribe",
             lambda: net.log(f"{name}.log"))
    return p


def start_send(net: Net, ns: str, cfg: dict, name: str):
    path = write_cfg(net.workdir / f"{name}.yaml", cfg)
    return net.pointflow(ns, "send", path, "--out", str(net.workdir / name), "-q", log=f"{name}.log")


#: Runs tests/remote/zenoh_probe.py with the transport's INFO lines logged (a sender alive,
#: gone, stopped), as a pipeline's source stage logs them.
_PROBE = ("import logging, runpy, sys; logging.basicConfig(level=logging.INFO, format='%(levelname)s %(message)s'); "
          "sys.argv = sys.argv[1:]; runpy.run_path(sys.argv[0], run_name='__main__')")


def start_probe(net: Net, ns: str, opts: dict, name: str, senders: int = 1):
    """The real zenoh transport in one process, until ``senders`` final syncs came
    (tests/remote/zenoh_probe.py): counters in NAME.json, positions in NAME.npy."""
    p = net.spawn(ns, sys.executable, "-c", _PROBE, str(REPO / "tests/remote/zenoh_probe.py"), json.dumps(opts),
                  str(net.workdir / name), str(senders), "240", log=f"{name}.log")
    wait_for(lambda: "probe: listening" in net.log(f"{name}.log"), 60, f"{name} to subscribe",
             lambda: net.log(f"{name}.log"))
    return p


def probe_counters(net: Net, name: str) -> dict:
    return json.loads((net.workdir / f"{name}.json").read_text())


def wait_ended(net: Net, name: str, senders: int) -> None:
    wait_for(lambda: net.log(f"{name}.log").count("stopped: sent") >= senders, 90,
             f"the senders' final syncs at {name}", lambda: net.log(f"{name}.log"))


def balanced(c: dict) -> bool:
    """The receiving identity: what was sent since it joined = received + lost in transit +
    dropped by its own bounded queue."""
    return c["link_sent"] == c["link_received"] + c["lost_in_transit"] + c.get("receive_queue_full", 0)


def router_stats(net: Net, name: str = "router") -> dict:
    return read_stats(net.workdir / name / "stats.json")["stages"]["router"]


def end_router(net: Net, p, name: str = "router") -> dict:
    assert stop(p) == 0, net.log(f"{name}.log")
    assert "Traceback" not in net.log(f"{name}.log")
    return router_stats(net, name)


# ----------------------------------------------------------------------------- tests
def test_two_sensors_through_a_router_to_two_viewers_over_mutual_tls(net):
    """The fan-out topology, every link mutual TLS: two sensor hosts publish through a router
    on a third host to two viewer pipelines; with backpressure (a replay) every point of each
    sensor arrives at both viewers, counted per sensor."""
    s1, s2, rt, v1, v2 = (net.host(n) for n in ("s1", "s2", "rt", "v1", "v2"))
    _, r_s1 = net.link(s1, rt)
    _, r_s2 = net.link(s2, rt)
    r_v1, _ = net.link(rt, v1)
    r_v2, _ = net.link(rt, v2)
    certs = net.workdir / "certs"
    make_certificate("router", certs, [r_s1, r_s2, r_v1, r_v2])  # it is reached at four addresses
    for n in ("sensor1", "sensor2", "viewer1", "viewer2"):
        make_certificate(n, certs)
    router = start_router(net, rt, f"tls/0.0.0.0:{PORT}", tls=tls_block(certs, "router"))
    views = {name: start_view(net, ns, view_cfg(zenoh_client(net, addr, tls_block(certs, name)), backpressure=True), name)
             for name, ns, addr in (("viewer1", v1, r_v1), ("viewer2", v2, r_v2))}
    sends = {name: start_send(net, ns, send_cfg(synthetic_source(src, scans=6), key, zenoh_client(net, addr, tls_block(certs, name)),
                                                backpressure=True), name)
             for name, ns, addr, src, key in (("sensor1", s1, r_s1, "left", "pf/site1"),
                                              ("sensor2", s2, r_s2, "right", "pf/site2"))}
    for name, p in sends.items():
        assert p.wait(120) == 0, net.log(f"{name}.log")
    sent = {src: read_stats(net.workdir / name / "stats.json")["accounting"]
            for name, src in (("sensor1", "left"), ("sensor2", "right"))}
    for src, a in sent.items():
        assert a["sender_balanced"] and a["lost_before_sender"] == 0 and a["sender_dropped"] == 0, a
        assert a["link_sent"] > 10_000
    for name, p in views.items():
        wait_ended(net, name, 2)
        assert stop(p) == 0, net.log(f"{name}.log")
        rcv = read_stats(net.workdir / name / "stats.json")
        ra, link = rcv["accounting"], rcv["stages"]["link"]
        for src, a in sent.items():  # every point of each sensor, counted per sensor
            assert link[f"transport_link_sent:{src}"] == a["link_sent"], (name, src, link)
        assert ra["lost_in_transit_by_source"] == {"left": 0, "right": 0}, ra
        assert ra.get("receive_queue_full", 0) == 0 and ra["link_balanced"], ra
        assert ra["link_received"] == sum(a["link_sent"] for a in sent.values()), ra
        # and on into the viewer's pipeline: ingested, or counted where its own queue dropped it
        assert ra["link_received"] == ra["ingest_received"] + ra["sources_dropped"] and ra["ingest_balanced"], ra
        assert link["transport_senders_lost"] == 0
    st = end_router(net, router)
    assert st["sessions_opened"] >= 4 and st["refused_connections"] == 0, st
    log = net.log("router.log")
    for n in ("sensor1", "sensor2", "viewer1", "viewer2"):  # each link authenticated by its certificate
        assert f"certificate {n}" in log, log


def test_a_viewer_that_joins_late(net):
    """A second viewer subscribes while the sensor is streaming: it gets what is sent after it
    joined, counts what came before as joined_after (not as lost), and its identity balances;
    the first viewer still gets everything."""
    s1, rt, v1, v2 = (net.host(n) for n in ("s1", "rt", "v1", "v2"))
    _, r_s1 = net.link(s1, rt)
    r_v1, _ = net.link(rt, v1)
    r_v2, _ = net.link(rt, v2)
    router = start_router(net, rt, f"tcp/0.0.0.0:{PORT}", insecure=True)
    early = start_probe(net, v1, {"key": "pf/**", "backpressure": True, "zenoh": zenoh_client(net, r_v1)}, "early")
    send = start_send(net, s1, send_cfg(synthetic_source(scans=150, points=2000, hz=10), "pf", zenoh_client(net, r_s1),
                                        backpressure=True), "send")
    # the late viewer joins once 300 KB of the stream went to the first one (of ~4.5 MB)
    wait_for(lambda: net.tx_bytes(rt, v1) > 300_000, 90, "the stream to reach the first viewer",
             lambda: net.log("send.log"))
    late = start_probe(net, v2, {"key": "pf/**", "backpressure": True, "zenoh": zenoh_client(net, r_v2)}, "late")
    assert send.wait(120) == 0, net.log("send.log")
    assert early.wait(120) == 0 and late.wait(120) == 0, net.log("early.log") + net.log("late.log")
    total = read_stats(net.workdir / "send" / "stats.json")["accounting"]["link_sent"]
    e, lt = probe_counters(net, "early"), probe_counters(net, "late")
    assert e["link_sent"] == e["link_received"] == total and e["lost_in_transit"] == 0 and e["joined_after"] == 0, e
    assert lt["ended"] == ["lidar"] and balanced(lt), lt
    assert lt["joined_after"] > 0, "the late viewer saw the stream from its start"
    assert lt["joined_after"] + lt["link_sent"] == total, (lt, total)
    assert lt["lost_in_transit"] == 0 and 0 < lt["link_received"] < e["link_received"], lt
    # what it got is the tail of what the first viewer got, point for point
    early_pos, late_pos = np.load(net.workdir / "early.npy"), np.load(net.workdir / "late.npy")
    assert np.array_equal(early_pos[-len(late_pos):], late_pos)
    end_router(net, router)


def test_router_killed_and_restarted(net):
    """The router host's `pointflow router` is killed (SIGKILL, all its processes) mid-stream
    and started again: sender and viewer reconnect by themselves, the viewer logs and counts
    the sender it lost sight of, and the points sent while no router ran are counted lost in
    transit: nothing is lost without being counted."""
    s1, rt, v1 = (net.host(n) for n in ("s1", "rt", "v1"))
    _, r_s1 = net.link(s1, rt)
    r_v1, _ = net.link(rt, v1)
    router = start_router(net, rt, f"tcp/0.0.0.0:{PORT}", insecure=True)
    probe = start_probe(net, v1, {"key": "pf/**", "zenoh": zenoh_client(net, r_v1)}, "view")
    send = start_send(net, s1, send_cfg(synthetic_source(scans=1_000_000, points=2000, hz=10), "pf",
                                        zenoh_client(net, r_s1)), "send")
    wait_for(lambda: net.tx_bytes(rt, v1) > 300_000, 90, "the stream to reach the viewer through the first router",
             lambda: net.log("send.log") + net.log("view.log"))
    os.killpg(router.pid, signal.SIGKILL)
    router.wait(10)
    wait_for(lambda: "is gone" in net.log("view.log"), 60, "the viewer to notice the sender is unreachable",
             lambda: net.log("view.log"))
    router2 = start_router(net, rt, f"tcp/0.0.0.0:{PORT}", name="router2", insecure=True)
    wait_for(lambda: net.log("router2.log").count("session opened") >= 2, 90, "both clients to reconnect",
             lambda: net.log("router2.log"))
    wait_for(lambda: net.log("view.log").count("is alive") >= 2, 60, "the sender seen alive again",
             lambda: net.log("view.log"))
    before = net.tx_bytes(rt, v1)
    wait_for(lambda: net.tx_bytes(rt, v1) > before + 300_000, 90, "the stream through the new router",
             lambda: net.log("send.log") + net.log("view.log"))
    assert stop(send, 60) == 0, net.log("send.log")  # the final sync goes through the new router
    assert probe.wait(120) == 0, net.log("view.log")
    snd = read_stats(net.workdir / "send" / "stats.json")["accounting"]
    c = probe_counters(net, "view")
    assert c["ended"] == ["lidar"] and c["link_sent"] == snd["link_sent"], (c, snd)
    assert balanced(c), c
    assert c["joined_after"] == 0, "the viewer got the stream from its start"
    assert c["lost_in_transit"] > 0, "points sent while no router ran must be counted lost"
    assert c["senders_lost"] >= 1 and c["link_received"] > 0
    st = end_router(net, router2, "router2")
    assert st["sessions_opened"] >= 2


def test_a_wrong_certificate_is_refused_and_counted(net):
    """An intruder whose certificate another CA signed cannot publish through the router: the
    router refuses the handshake and counts it (stats and log), the intruder's `pointflow
    send` fails with the reason, and the authorised sensor's points all arrive."""
    s1, bad, rt, v1 = (net.host(n) for n in ("s1", "bad", "rt", "v1"))
    _, r_s1 = net.link(s1, rt)
    _, r_bad = net.link(bad, rt)
    r_v1, _ = net.link(rt, v1)
    certs = net.workdir / "certs"
    make_certificate("router", certs, [r_s1, r_bad, r_v1])
    for n in ("sensor", "viewer"):
        make_certificate(n, certs)
    make_certificate("intruder", net.workdir / "other-ca", [r_bad])
    router = start_router(net, rt, f"tls/0.0.0.0:{PORT}", tls=tls_block(certs, "router"))
    probe = start_probe(net, v1, {"key": "pf/**", "backpressure": True,
                                  "zenoh": zenoh_client(net, r_v1, tls_block(certs, "viewer"))}, "view")
    # the intruder trusts the real CA (it knows the router's certificate) but its own is foreign
    intruder = start_send(net, bad, send_cfg(synthetic_source("evil", scans=3), "pf",
                                             zenoh_client(net, r_bad, tls_block(certs, "intruder"))), "intruder")
    assert intruder.wait(120) == 2, net.log("intruder.log")
    assert "Unable to connect" in net.log("intruder.log") and "Traceback" not in net.log("intruder.log")
    wait_for(lambda: "refused a connection" in net.log("router.log"), 30, "the refusal in the router's log",
             lambda: net.log("router.log"))
    send = start_send(net, s1, send_cfg(synthetic_source(scans=6), "pf", zenoh_client(net, r_s1, tls_block(certs, "sensor")),
                                        backpressure=True), "send")
    assert send.wait(120) == 0, net.log("send.log")
    assert probe.wait(120) == 0, net.log("view.log")
    c = probe_counters(net, "view")
    total = read_stats(net.workdir / "send" / "stats.json")["accounting"]["link_sent"]
    assert c["ended"] == ["lidar"] and c["link_received"] == c["link_sent"] == total > 0, c
    assert "link_sent:evil" not in c  # not one message of the intruder's got through
    st = end_router(net, router)
    assert st["refused_connections"] >= 1 and "UnknownIssuer" in " ".join(st["rejected"]), st
    assert " refused (last: invalid peer certificate: UnknownIssuer)" in net.log("router.log")


def test_a_slow_viewer_loses_only_its_own_data(net):
    """One viewer behind a slow link (tbf 1 Mbit/s on the router's side for 3 s), live data:
    the sensor never waits, the router drops for that viewer only, and the slow viewer counts
    every point it did not get. The fast viewer's link is not the bottleneck: on a quiet
    machine it gets everything; on a busy one it may lose some too (CPU, not the slow link),
    counted the same way, and fewer than the slow one."""
    s1, rt, fast, slow = (net.host(n) for n in ("s1", "rt", "fast", "slow"))
    _, r_s1 = net.link(s1, rt)
    r_fast, _ = net.link(rt, fast)
    r_slow, _ = net.link(rt, slow)
    # the router's kernel send buffers small (Zenoh's own queue stays 16 batches of 64 KiB): a
    # backlog builds in Zenoh's queue, where it is dropped for that viewer, not seconds of it
    # in the kernel
    router = start_router(net, rt, f"tcp/0.0.0.0:{PORT}", insecure=True,
                          config_file=net_config(net, "tcp: {so_sndbuf: 65536}", "router-zenoh"))
    pf = start_probe(net, fast, {"key": "pf/**", "queue_chunks": 256, "zenoh": zenoh_client(net, r_fast)}, "fast")
    ps = start_probe(net, slow, {"key": "pf/**", "queue_chunks": 256, "zenoh": zenoh_client(net, r_slow)}, "slow")
    send = start_send(net, s1, send_cfg(synthetic_source(scans=200, points=8000, hz=10), "pf", zenoh_client(net, r_s1)),
                      "send")
    wait_for(lambda: "every source has a subscriber" in net.log("send.log"), 60, "the sender to start",
             lambda: net.log("send.log"))
    # far below what the sensor sends even when it is starved of CPU (~3 Mbit/s at load 20),
    # until 400 KB went through it: about 6 s of a saturated link, wherever the stream starts
    net.qdisc(rt, slow, "tbf", "rate", "512kbit", "burst", "32kbit", "latency", "400ms")
    wait_for(lambda: net.qdisc_sent(rt, slow) >= 400_000, 120, "the throttled link to carry 400 KB")
    net.del_qdisc(rt, slow)
    assert send.wait(120) == 0, net.log("send.log")
    assert pf.wait(120) == 0 and ps.wait(120) == 0, net.log("fast.log") + net.log("slow.log")
    snd = read_stats(net.workdir / "send" / "stats.json")
    assert snd["stages"]["sender"]["drops"] == {} and snd["stages"]["lidar"]["drops"] == {}, "the sensor waited"
    total = snd["accounting"]["link_sent"]
    f, s = probe_counters(net, "fast"), probe_counters(net, "slow")
    for c in (f, s):
        assert c["ended"] == ["lidar"] and c["link_sent"] == total and balanced(c), c
    missed = lambda c: c["lost_in_transit"] + c.get("receive_queue_full", 0)  # noqa: E731
    assert missed(s) > 0, "the slow link was not the bottleneck"
    assert missed(f) < missed(s), (f, s)
    end_router(net, router)
