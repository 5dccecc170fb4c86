"""Separate hosts on one machine for the link tests: Linux network namespaces joined by
veth pairs (``ip netns``, ``ip link``), processes started inside them with
``ip netns exec``, and a cleanup that removes all of it however a test ends.

Names start with ``pf-`` (namespaces) and ``pf`` (veth ends) plus a random suffix, so
concurrent runs do not collide and :func:`sweep_leftovers` can find what a killed run
left behind. Addresses live only inside the namespaces a test creates (10.231.x.y/24).
"""
from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
PREFIX = "pf-"


def ci() -> bool:
    return os.environ.get("CI", "").lower() in ("1", "true", "yes")


def unavailable_reason() -> str | None:
    """Why namespaces cannot be made here, or None."""
    if shutil.which("ip") is None:
        return "the `ip` tool (iproute2) is missing: run scripts/install-system-deps.sh"
    if os.geteuid() != 0:
        return "network-namespace tests need root"
    return None


def require_netns() -> None:
    """Skip without root or ``ip``; under CI=true fail instead (CI must run these)."""
    why = unavailable_reason()
    if why:
        if ci():
            pytest.fail(f"CI=true but {why}")
        pytest.skip(why)


def sh(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    p = subprocess.run(list(args), capture_output=True, text=True, timeout=30)
    if check and p.returncode:
        raise RuntimeError(f"{' '.join(args)} failed ({p.returncode}): {p.stderr.strip()}")
    return p


def list_namespaces() -> list[str]:
    out = sh("ip", "netns", "list", check=False).stdout
    return [line.split()[0] for line in out.splitlines() if line.strip()]


def _ns_pids(ns: str) -> list[int]:
    out = sh("ip", "netns", "pids", ns, check=False).stdout
    return [int(x) for x in out.split() if x.strip().isdigit()]


def delete_namespace(ns: str) -> None:
    """Kill what still runs in ``ns`` (by pid), then delete it (its veth ends go with it)."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        pids = _ns_pids(ns)
        for pid in pids:
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass
        end = time.monotonic() + 3
        while pids and time.monotonic() < end:
            time.sleep(0.05)
            pids = _ns_pids(ns)
        if not pids:
            break
    sh("ip", "netns", "del", ns, check=False)


#: A namespace younger than this is never swept: another test run may have just made it
#: (each Net also keeps a process in its namespaces, see Net.host).
SWEEP_MIN_AGE_S = 120.0


def _age_s(ns: str) -> float:
    try:
        return time.time() - os.stat(f"/run/netns/{ns}").st_mtime
    except OSError:
        return float("inf")


def sweep_leftovers() -> list[str]:
    """Delete ``pf-*`` namespaces no process uses (left by a killed test run)."""
    gone = []
    for ns in list_namespaces():
        if ns.startswith(PREFIX) and _age_s(ns) > SWEEP_MIN_AGE_S and not _ns_pids(ns):
            sh("ip", "netns", "del", ns, check=False)
            gone.append(ns)
    return gone


#: Nets not closed yet: what a SIGTERM of the test run must remove.
_OPEN: "set[Net]" = set()


def _on_sigterm(signum, frame) -> None:
    """The test run got SIGTERM (a CI timeout, ``kill``): Python's default would end it at
    once, leaving namespaces and the ``pointflow`` processes in them (their own sessions,
    so nothing else reaches them). Remove them first, then end the run as Ctrl-C does."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second SIGTERM must not cut the cleanup short
    for n in list(_OPEN):
        try:
            n.close()
        except Exception:  # noqa: BLE001 - clean up the others anyway
            pass
    pytest.exit("stopped by SIGTERM; namespaces and link processes removed", returncode=128 + signal.SIGTERM)


def _install_sigterm_handler() -> None:
    if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGTERM) is not _on_sigterm:
        signal.signal(signal.SIGTERM, _on_sigterm)


class Net:
    """Namespaces, links and processes of one test; :meth:`close` removes them all (also
    when the test run is stopped with SIGTERM)."""

    def __init__(self, workdir: Path):
        _install_sigterm_handler()
        _OPEN.add(self)
        self.tag = secrets.token_hex(3)
        self.workdir = workdir
        self.namespaces: list[str] = []
        self.procs: list[subprocess.Popen] = []
        self._links = 0
        self.veths: dict[tuple[str, str], str] = {}

    def host(self, name: str) -> str:
        ns = f"{PREFIX}{self.tag}-{name}"
        sh("ip", "netns", "add", ns)
        self.namespaces.append(ns)
        sh("ip", "-n", ns, "link", "set", "lo", "up")
        # a process in it from the start: another test run's sweep_leftovers (namespaces no
        # process uses) must not take it before this test starts its own there
        self.procs.append(subprocess.Popen(["ip", "netns", "exec", ns, "sleep", "infinity"],
                                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                           start_new_session=True))
        return ns

    def link(self, a: str, b: str) -> tuple[str, str]:
        """A veth pair between namespaces ``a`` and ``b``; returns (address in a, address in b)."""
        k = self._links
        self._links += 1
        ea, eb = f"pf{self.tag}{k}a", f"pf{self.tag}{k}b"
        sh("ip", "link", "add", ea, "type", "veth", "peer", "name", eb)
        sh("ip", "link", "set", ea, "netns", a)
        sh("ip", "link", "set", eb, "netns", b)
        subnet = f"10.231.{(int(self.tag, 16) + k) % 250}"
        sh("ip", "-n", a, "addr", "add", f"{subnet}.1/24", "dev", ea)
        sh("ip", "-n", b, "addr", "add", f"{subnet}.2/24", "dev", eb)
        sh("ip", "-n", a, "link", "set", ea, "up")
        sh("ip", "-n", b, "link", "set", eb, "up")
        self.veths[(a, b)] = ea
        self.veths[(b, a)] = eb
        return f"{subnet}.1", f"{subnet}.2"

    def set_link(self, ns: str, peer: str, up: bool) -> None:
        sh("ip", "-n", ns, "link", "set", self.veths[(ns, peer)], "up" if up else "down")

    def qdisc(self, ns: str, peer: str, kind: str, *spec: str) -> None:
        """``tc qdisc add ... root KIND SPEC`` on ``ns``'s end of the link to ``peer``.

        A kernel built without that qdisc (the Firecracker kernels these tests run on have no
        sch_netem, and no modules to load) skips the test even under CI=true: nothing the
        project installs can add it. ``POINTFLOW_REQUIRE_NETEM=1`` turns that into a failure."""
        p = sh("ip", "netns", "exec", ns, "tc", "qdisc", "add", "dev", self.veths[(ns, peer)], "root", kind, *spec,
               check=False)
        if p.returncode:
            why = f"tc qdisc {kind} is not available here: {p.stderr.strip()}"
            if "unknown" in p.stderr and os.environ.get("POINTFLOW_REQUIRE_NETEM") != "1":
                pytest.skip(why + " (this kernel lacks sch_" + kind + ")")
            raise RuntimeError(why)

    def tx_bytes(self, ns: str, peer: str) -> int:
        """Bytes ``ns``'s end of the link to ``peer`` has sent (the kernel's counter)."""
        out = sh("ip", "-n", ns, "-s", "-j", "link", "show", "dev", self.veths[(ns, peer)]).stdout
        return int(json.loads(out)[0]["stats64"]["tx"]["bytes"])

    def qdisc_sent(self, ns: str, peer: str) -> int:
        """Bytes the root qdisc on ``ns``'s end of the link to ``peer`` has sent."""
        out = sh("ip", "netns", "exec", ns, "tc", "-s", "qdisc", "show", "dev", self.veths[(ns, peer)]).stdout
        return int(out.split("Sent ", 1)[1].split(" ", 1)[0])

    def del_qdisc(self, ns: str, peer: str) -> None:
        sh("ip", "netns", "exec", ns, "tc", "qdisc", "del", "dev", self.veths[(ns, peer)], "root")

    def spawn(self, ns: str, *argv: str, log: str) -> subprocess.Popen:
        """Start ``argv`` inside ``ns`` (stdout+stderr to ``workdir/log``)."""
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        f = open(self.workdir / log, "w")
        p = subprocess.Popen(["ip", "netns", "exec", ns, *argv], stdout=f, stderr=subprocess.STDOUT,
                             env=env, cwd=str(self.workdir), start_new_session=True)
        f.close()
        self.procs.append(p)
        return p

    def pointflow(self, ns: str, *args: str, log: str) -> subprocess.Popen:
        return self.spawn(ns, sys.executable, "-m", "pointflow.cli", *args, log=log)

    def log(self, name: str) -> str:
        try:
            return (self.workdir / name).read_text()
        except OSError:
            return ""

    def close(self) -> None:
        _OPEN.discard(self)
        for p in self.procs:
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGTERM)
                except ProcessLookupError:
                    pass
        end = time.monotonic() + 8
        for p in self.procs:
            try:
                p.wait(max(0.1, end - time.monotonic()))
            except subprocess.TimeoutExpired:
                try:
                    os.killpg(p.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                p.wait(5)
        for ns in self.namespaces:
            delete_namespace(ns)
        self.namespaces.clear()
        from pointflow.ring.sweep import sweep_orphans

        sweep_orphans()


def stop(p: subprocess.Popen, timeout: float = 20.0) -> int:
    """SIGTERM a ``pointflow run`` (it stops its stages in order and writes stats.json) and
    wait. Only the supervisor gets the signal (``ip netns exec`` execs it, same pid): the
    stages would otherwise stop on their own at once, and it would see them die."""
    if p.poll() is None:
        os.kill(p.pid, signal.SIGTERM)
    return p.wait(timeout)


def read_stats(path: Path) -> dict:
    return json.loads(Path(path).read_text())
