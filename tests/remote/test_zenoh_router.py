"""`pointflow router` and `pointflow keys --tls` on one host (loopback): a real router
process, real Zenoh client sessions in the test, real certificates and TLS handshakes
(docs/remote.md, "Routers and TLS"). The topologies across hosts are in
test_zenoh_topologies.py."""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import psutil
import pytest

zenoh = pytest.importorskip("zenoh", reason="eclipse-zenoh comes with the remote extra: pip install 'pointflow[remote]'")

from pointflow.cli import main as cli_main  # noqa: E402
from pointflow.remote.tls import make_certificate  # noqa: E402
from pointflow.remote.zenoh_options import (ZenohOpenError, ZenohOptions, ZenohTls, check_zenoh,  # noqa: E402
                                            open_session)
from pointflow.testing import free_port  # noqa: E402

from .helpers import wait_for  # noqa: E402


class Routers:
    """`pointflow router` processes of one test, stopped however the test ends."""

    def __init__(self, tmp: Path):
        self.tmp = tmp
        self.procs: list[subprocess.Popen] = []

    def start(self, router: dict, name: str = "router", *args: str) -> subprocess.Popen:
        cfg = self.tmp / f"{name}.yaml"
        # a router silent for a second on a machine at load 10+ is not taken for hung
        cfg.write_text(json.dumps({"router": {"stats_every_s": 0.5, **router}, "supervisor": {"hung_after_ms": 10_000}}))
        log = open(self.tmp / f"{name}.log", "w")
        p = subprocess.Popen([sys.executable, "-m", "pointflow.cli", "router", str(cfg), "--out",
                              str(self.tmp / name), *args], stdout=log, stderr=subprocess.STDOUT,
                             cwd=str(self.tmp), start_new_session=True, env=dict(os.environ, PYTHONUNBUFFERED="1"))
        log.close()
        self.procs.append(p)
        return p

    def log(self, name: str = "router") -> str:
        return (self.tmp / f"{name}.log").read_text()

    def wait_up(self, name: str = "router") -> None:
        wait_for(lambda: " listening on " in self.log(name), 60, f"{name} to listen", lambda: self.log(name))

    def stats(self, name: str = "router") -> dict:
        return json.loads((self.tmp / name / "stats.json").read_text())

    def close(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(10)


@pytest.fixture
def routers(tmp_path):
    r = Routers(tmp_path)
    try:
        yield r
    finally:
        r.close()


@pytest.fixture
def sessions():
    """Open Zenoh sessions in the test; each is closed at the end (an open session with
    callbacks keeps the interpreter from exiting)."""
    opened: list = []

    def open_(o: ZenohOptions, base_dir: str = "/"):
        check_zenoh(o, "zenoh", base_dir)
        s = open_session(o)
        opened.append(s)
        return s

    yield open_
    for s in opened:
        s.close()


def client(port: int, scheme: str = "tcp", tls: ZenohTls | None = None) -> ZenohOptions:
    return ZenohOptions(mode="client", connect=[f"{scheme}/127.0.0.1:{port}"], tls=tls)


class Inbox:
    """Samples a subscriber got, by key."""

    def __init__(self, session, keyexpr: str):
        self.got: list[tuple[str, bytes]] = []
        self.sub = session.declare_subscriber(keyexpr, lambda s: self.got.append((str(s.key_expr),
                                                                                   s.payload.to_bytes())))

    def keys(self) -> list[str]:
        return [k for k, _ in self.got]


def exchange(pub_session, inbox: Inbox, key: str, n: int, timeout: float = 30) -> None:
    """Put ``n`` numbered samples on ``key`` once the subscription has reached the publisher's
    router (retrying the first until it arrives), then wait for all of them."""
    pub = pub_session.declare_publisher(key)
    try:
        wait_for(lambda: (pub.put(b"hello"), any(k == key and p == b"hello" for k, p in inbox.got))[1], timeout,
                 "the first sample through the router")
        for i in range(n):
            pub.put(i.to_bytes(4, "little"))
        wait_for(lambda: sum(1 for k, p in inbox.got if k == key and p != b"hello") >= n, timeout,
                 f"{n} samples on {key}")
    finally:
        pub.undeclare()
    assert [int.from_bytes(p, "little") for k, p in inbox.got if k == key and p != b"hello"] == list(range(n))


# ----------------------------------------------------------------------------- keys --tls
def test_keys_tls_makes_one_ca_and_certificates_it_signed(tmp_path, capsys):
    from cryptography import x509

    d = tmp_path / "certs"
    assert cli_main(["keys", "router", "--tls", "--dir", str(d), "--host", "10.231.0.2", "--host", "router1"]) == 0
    ca_bytes = (d / "ca.pem").read_bytes()
    assert "CA:" in capsys.readouterr().out
    assert cli_main(["keys", "viewer", "--tls", "--dir", str(d)]) == 0
    assert (d / "ca.pem").read_bytes() == ca_bytes, "the CA was made again instead of reused"
    ca = x509.load_pem_x509_certificate(ca_bytes)
    for name, names in (("router", {"router", "router1", "10.231.0.2"}), ("viewer", {"viewer", "localhost", "127.0.0.1"})):
        cert = x509.load_pem_x509_certificate((d / f"{name}.pem").read_bytes())
        cert.verify_directly_issued_by(ca)  # raises when another key signed it
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert {str(v) for v in san.get_values_for_type(x509.DNSName)} | \
               {str(v) for v in san.get_values_for_type(x509.IPAddress)} == names
        assert cert.subject.rfc4514_string() == f"CN={name}"
        assert (d / f"{name}-key.pem").stat().st_mode & 0o777 == 0o600
    assert (d / "ca-key.pem").stat().st_mode & 0o777 == 0o600
    capsys.readouterr()
    # refusals: one line each, exit 1, nothing overwritten
    assert cli_main(["keys", "viewer", "--tls", "--dir", str(d)]) == 1
    assert "already exists" in capsys.readouterr().err
    assert cli_main(["keys", "x", "--tls", "--dir", str(d), "--host", "bad host!"]) == 1
    assert "neither an IP address nor a host name" in capsys.readouterr().err
    assert cli_main(["keys", "x", "--dir", str(d), "--host", "h"]) == 1
    assert "add --tls" in capsys.readouterr().err
    (d / "ca-key.pem").unlink()
    assert cli_main(["keys", "other", "--tls", "--dir", str(d)]) == 1
    assert "ca-key.pem is not here" in capsys.readouterr().err
    assert not (d / "other.pem").exists()


# ----------------------------------------------------------------------------- router
def test_router_carries_samples_between_clients_and_reports_its_sessions(routers, sessions):
    port = free_port()
    p = routers.start({"listen": [f"tcp/127.0.0.1:{port}"]})
    routers.wait_up()
    a, b = sessions(client(port)), sessions(client(port))
    inbox = Inbox(b, "pf/**")
    exchange(a, inbox, "pf/lidar", 200)
    wait_for(lambda: "2 session(s) connected (2 clients)" in routers.log(), 30, "the router to list both clients",
             routers.log)
    p.send_signal(signal.SIGINT)
    assert p.wait(30) == 0, routers.log()
    st = routers.stats()["stages"]["router"]
    assert st["sessions_opened"] >= 2 and st["refused_connections"] == 0 and st["restarts"] == 0
    assert st["listen"] == [f"tcp/127.0.0.1:{port}"] and not st["alive"]
    assert "Traceback" not in routers.log() and "stopped by SIGINT" in routers.log()
    assert routers.log().count("session opened: client") >= 2


def test_router_stage_killed_is_restarted_and_clients_reconnect(routers, sessions):
    port = free_port()
    p = routers.start({"listen": [f"tcp/127.0.0.1:{port}"]})
    routers.wait_up()
    a, b = sessions(client(port)), sessions(client(port))
    inbox = Inbox(b, "pf/**")
    exchange(a, inbox, "pf/before", 10)
    # once the supervisor has heard of both sessions, they count in its totals after the kill
    wait_for(lambda: "2 session(s) connected" in routers.log(), 30, "the sessions in the router's line", routers.log)
    (stage,) = psutil.Process(p.pid).children()
    stage.kill()
    wait_for(lambda: "restarting router" in routers.log(), 30, "the supervisor to restart the router", routers.log)
    # the clients reconnect by themselves; samples flow again through the new router process
    exchange(a, inbox, "pf/after", 10, timeout=60)
    assert [c.pid for c in psutil.Process(p.pid).children()] != [stage.pid]
    p.send_signal(signal.SIGTERM)
    assert p.wait(30) == 0, routers.log()
    st = routers.stats()
    assert st["stages"]["router"]["restarts"] == 1
    assert st["events"][0]["reason"] == "killed by signal SIGKILL" and st["events"][0]["action"] == "restart"
    assert st["stages"]["router"]["sessions_opened"] >= 4  # both clients, before and after
    assert "Traceback" not in routers.log()


@pytest.fixture
def pki(tmp_path):
    """One CA with router, sensor and viewer certificates; another CA with an intruder's."""
    good, bad = tmp_path / "certs", tmp_path / "other-ca"
    for n in ("router", "sensor", "viewer"):
        make_certificate(n, good)
    make_certificate("intruder", bad)

    def tls(name: str, ca_dir: Path = good, **kw) -> ZenohTls:
        d = bad if name == "intruder" else good
        return ZenohTls(root_ca=str(ca_dir / "ca.pem"), certificate=str(d / f"{name}.pem"),
                        private_key=str(d / f"{name}-key.pem"), **kw)

    tls.good = good
    return tls


def test_mutual_tls_through_the_router_and_a_foreign_certificate_is_refused(routers, sessions, pki):
    port = free_port()
    p = routers.start({"listen": [f"tls/127.0.0.1:{port}"],
                       "tls": {"root_ca": str(pki.good / "ca.pem"), "certificate": str(pki.good / "router.pem"),
                               "private_key": str(pki.good / "router-key.pem")}})
    routers.wait_up()
    sensor = sessions(client(port, "tls", pki("sensor")))
    viewer = sessions(client(port, "tls", pki("viewer")))
    inbox = Inbox(viewer, "pf/**")
    exchange(sensor, inbox, "pf/lidar", 50)
    # an intruder whose certificate another CA signed: the router refuses the handshake
    with pytest.raises(ZenohOpenError, match="Unable to connect"):
        sessions(client(port, "tls", pki("intruder")))
    # a client that presents no certificate at all (mutual TLS is the router's rule)
    with pytest.raises(ZenohOpenError):
        sessions(client(port, "tls", ZenohTls(root_ca=str(pki.good / "ca.pem"), mutual=False)))
    wait_for(lambda: routers.log().count("refused a connection") >= 2, 30, "both refusals in the router's log",
             routers.log)
    wait_for(lambda: " 2 refused" in routers.log(), 30, "the refusals in the router's session line", routers.log)
    assert "UnknownIssuer" in routers.log()

    def listed():
        line = [x for x in routers.log().splitlines() if "session(s) connected" in x][-1]
        return "2 session(s) connected (2 clients)" in line

    wait_for(listed, 30, "the two clients still connected", routers.log)
    exchange(sensor, inbox, "pf/still", 5)  # the refusals did not disturb the authorised ones
    p.send_signal(signal.SIGTERM)
    assert p.wait(30) == 0, routers.log()
    st = routers.stats()["stages"]["router"]
    assert st["refused_connections"] == sum(st["rejected"].values()) >= 2
    reasons = " | ".join(st["rejected"])
    assert "UnknownIssuer" in reasons and "no certificates" in reasons, st["rejected"]


def test_router_lists_the_certificate_name_of_each_tls_link(routers, sessions, pki, tmp_path):
    port = free_port()
    p = routers.start({"listen": [f"tls/127.0.0.1:{port}"],
                       "tls": {"root_ca": str(pki.good / "ca.pem"), "certificate": str(pki.good / "router.pem"),
                               "private_key": str(pki.good / "router-key.pem")}}, "router", "--duration", "600")
    routers.wait_up()
    sessions(client(port, "tls", pki("sensor")))
    sessions(client(port, "tls", pki("viewer")))
    wait_for(lambda: "certificate viewer" in routers.log() and "certificate sensor" in routers.log(), 30,
             "both links logged with their certificate names", routers.log)
    p.send_signal(signal.SIGINT)
    assert p.wait(30) == 0, routers.log()


ACL = """{
  access_control: {
    enabled: true,
    default_permission: "allow",
    rules: [{ id: "no-secrets", permission: "deny", flows: ["ingress", "egress"],
              messages: ["put", "delete", "declare_subscriber"], key_exprs: ["pf/secret/**"] }],
    subjects: [{ id: "everyone" }],
    policies: [{ rules: ["no-secrets"], subjects: ["everyone"] }],
  },
}
"""


def test_an_access_control_rule_in_the_config_file_stops_delivery(routers, sessions, tmp_path):
    (tmp_path / "acl.json5").write_text(ACL)
    port = free_port()
    p = routers.start({"listen": [f"tcp/127.0.0.1:{port}"], "config_file": "acl.json5"})
    routers.wait_up()
    a, b = sessions(client(port)), sessions(client(port))
    inbox = Inbox(b, "pf/**")
    exchange(a, inbox, "pf/open/lidar", 5)
    # the same session, through the same router, in order: the secret samples go first
    for i in range(20):
        a.put("pf/secret/lidar", b"x")
    exchange(a, inbox, "pf/open/tail", 5)
    assert not [k for k in inbox.keys() if k.startswith("pf/secret")]
    p.send_signal(signal.SIGINT)
    assert p.wait(30) == 0, routers.log()


def test_router_errors_are_one_line_without_traceback(tmp_path):
    def run(router: dict, *args: str) -> subprocess.CompletedProcess:
        cfg = tmp_path / "r.yaml"
        cfg.write_text(json.dumps({"router": router}))
        return subprocess.run([sys.executable, "-m", "pointflow.cli", "router", str(cfg), *args], capture_output=True,
                              text=True, timeout=120, cwd=str(tmp_path))

    r = run({"listen": ["tcp/0.0.0.0:7447"]})
    assert r.returncode == 1 and "router.listen[0]" in r.stderr and "in the clear" in r.stderr, r.stderr
    r = run({"listen": ["tls/127.0.0.1:7447"]})
    assert r.returncode == 1 and "router.tls is not set" in r.stderr, r.stderr
    r = run({"mode": "peer"})
    assert r.returncode == 1 and "router.mode" in r.stderr, r.stderr
    r = run({"config_file": "missing.json5"})
    assert r.returncode == 1 and "router.config_file" in r.stderr, r.stderr
    with socket.socket() as taken:  # the port belongs to another program: the run fails at once
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        r = run({"listen": [f"tcp/127.0.0.1:{port}"]}, "--duration", "60")
    assert r.returncode == 2 and "Address already in use" in r.stderr, r.stderr
    for out in (r.stderr, r.stdout):
        assert "Traceback" not in out and ".rs:" not in out
    (tmp_path / "src.yaml").write_text("source: {transport: synthetic}\n")
    r = subprocess.run([sys.executable, "-m", "pointflow.cli", "router", "src.yaml"], capture_output=True, text=True,
                       timeout=60, cwd=str(tmp_path))
    assert r.returncode == 1 and "no 'router:' section" in r.stderr
    r = subprocess.run([sys.executable, "-m", "pointflow.cli", "run", "r.yaml"], capture_output=True, text=True,
                       timeout=60, cwd=str(tmp_path))
    assert r.returncode == 1 and "pointflow router" in r.stderr


def test_the_router_config_of_the_repo_validates():
    from pointflow.config import load_config

    cfg = load_config(Path(__file__).resolve().parents[2] / "configs" / "zenoh-router.yaml")
    assert cfg.router.mode == "router" and cfg.router.listen == ["tcp/127.0.0.1:7447"] and not cfg.sources


def test_two_routers_meshed_carry_samples_between_their_clients(routers, sessions):
    """A router that connects to another (`connect:`): a client of one reaches a client of
    the other, as across two networks, and each lists the other as a router session."""
    pa, pb = free_port(), free_port()
    a = routers.start({"listen": [f"tcp/127.0.0.1:{pa}"]}, "a")
    routers.wait_up("a")
    b = routers.start({"listen": [f"tcp/127.0.0.1:{pb}"], "connect": [f"tcp/127.0.0.1:{pa}"]}, "b")
    routers.wait_up("b")
    wait_for(lambda: "(1 router)" in routers.log("a") and "(1 router)" in routers.log("b"), 30,
             "the routers to see each other", lambda: routers.log("a") + routers.log("b"))
    sensor, viewer = sessions(client(pa)), sessions(client(pb))
    inbox = Inbox(viewer, "pf/**")
    exchange(sensor, inbox, "pf/lidar", 50)
    for p, name in ((a, "a"), (b, "b")):
        p.send_signal(signal.SIGINT)
        assert p.wait(30) == 0, routers.log(name)


def test_engine_log_lines_are_parsed_counted_and_relogged(caplog):
    """Lines as the engine writes them (captured from eclipse-zenoh 1.10 with its colours):
    refused TLS handshakes are counted by reason, other warnings logged, nothing lost."""
    import logging

    from pointflow.remote.zenoh_log import EngineLog

    log = logging.getLogger("pointflow.test.engine")
    e = EngineLog(log)
    with caplog.at_level(logging.INFO, logger="pointflow.test.engine"):
        e.feed("\x1b[2m2026-11-23T22:55:53.410763Z\x1b[0m \x1b[33m WARN\x1b[0m acc-0 ThreadId(05) "
               "\x1b[2mzenoh_link_tls::unicast\x1b[0m\x1b[2m:\x1b[0m invalid peer certificate: UnknownIssuer. "
               "Hint: increase the system open file limit.\n")
        e.feed("2026-11-23T23:04:01.1Z  WARN acc-0 ThreadId(07) zenoh_link_tls::unicast: peer sent no certificates\n")
        e.feed("2026-11-23T22:55:53.411307Z  WARN ThreadId(01) zenoh::net::runtime::orchestrator: Unable to connect "
               "to tls/127.0.0.1:17447! received fatal alert: UnknownCA at /root/.cargo/git/x/unicast.rs:226.\n")
        e.feed("something the engine printed without a level\n")
    assert e.counts() == {"invalid peer certificate: UnknownIssuer": 1, "peer sent no certificates": 1}
    assert e.last_refusal == "peer sent no certificates"
    text = caplog.text
    assert text.count("refused a connection") == 2 and "Hint" not in text
    assert "Unable to connect to tls/127.0.0.1:17447! received fatal alert: UnknownCA" in text and ".rs:" not in text
    assert "something the engine printed" in text and e.lines == 4


def test_a_killed_zenoh_session_leaves_nothing_in_dev_shm():
    """pointflow's sessions run without Zenoh's shared-memory transport, which keeps a file in
    /dev/shm per process that a killed process leaves behind (seen after a loaded test run)."""
    code = ("import time\nfrom pointflow.remote.zenoh_options import ZenohOptions, open_session\n"
            "s = open_session(ZenohOptions(mode='peer'))\nprint('open', flush=True)\ntime.sleep(60)\n")
    before = set(os.listdir("/dev/shm"))
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "open"
        assert not [f for f in set(os.listdir("/dev/shm")) - before if f.endswith(".zenoh")]
    finally:
        p.kill()
        p.wait()
        p.stdout.close()
    assert not [f for f in set(os.listdir("/dev/shm")) - before if f.endswith(".zenoh")]
