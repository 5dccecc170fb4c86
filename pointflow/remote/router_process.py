"""``pointflow router CONFIG``: a Zenoh router in its own process, supervised like a stage.

Sensors (``send: {engine: zenoh}``) and viewers (the ``zenoh`` transport) in client mode
connect to a router; it forwards each sample once per subscriber, so a sensor host sends
every byte once however many viewers there are, and routers connected to each other cross
networks. This is a Python Zenoh session in ``router`` mode (no ``zenohd`` needed) run by
the supervisor as the stage ``router``: restarted with backoff if it dies, stopped on
SIGINT/SIGTERM. Its heartbeat carries the sessions connected now (clients, peers,
routers, with the certificate name of each TLS link) and the connections opened, closed
and refused; refused TLS handshakes are read from the engine's log
(:mod:`.zenoh_log`), since Zenoh's API reports only transports that opened.
"""
from __future__ import annotations

import threading
import time
from typing import Any

from ..stage.kinds import StageKind, register_stage_kind
from .zenoh_options import RouterConfig, ZenohOpenError, open_session

#: ``pointflow router``: this one stage, no ring; connections counted over its restarts.
KIND = register_stage_kind(StageKind(name="router", main="pointflow.remote.router_process:main", start_order=35, stop_wave=1,
                                     roles=("router",),
                                     counters=("sessions_opened", "sessions_closed", "refused_connections")))

#: At most this many sessions are listed in the stats (all are counted).
MAX_LISTED = 64
#: A restarted router may find its port still held for a moment: retry opening this long.
OPEN_RETRY_S = 5.0


class SessionTable:
    """Who is connected to the router, from the session's transports and links, and the
    connections opened and closed since it started (from the transport events)."""

    def __init__(self, log):
        self.log = log
        self.opened = 0
        self.closed = 0
        self._kind: dict[str, str] = {}
        # Zenoh reports a session's link and its transport through two listeners, in no fixed
        # order: a link seen before its transport waits here so its line can name the kind.
        self._pending: dict[str, list[tuple[str, str]]] = {}
        self._lock = threading.Lock()

    def on_transport(self, ev) -> None:
        import zenoh

        t = ev.transport
        zid, kind = str(t.zid), str(t.whatami).rsplit(".", 1)[-1].lower()
        with self._lock:
            if ev.kind == zenoh.SampleKind.PUT:
                self.opened += 1
                self._kind[zid] = kind
                for dst, cert in self._pending.pop(zid, []):
                    self._log_opened(kind, zid, dst, cert)
            else:
                self.closed += 1
                self._kind.pop(zid, None)
                for dst, cert in self._pending.pop(zid, []):
                    self._log_opened(kind, zid, dst, cert)
                self.log.info("session closed: %s %s", kind, zid)

    def on_link(self, ev) -> None:
        import zenoh

        if ev.kind != zenoh.SampleKind.PUT:
            return
        ln = ev.link
        zid = str(ln.zid)
        cert = f", certificate {ln.auth_identifier}" if ln.auth_identifier else ""
        with self._lock:
            kind = self._kind.get(zid)
            if kind is None:
                self._pending.setdefault(zid, []).append((str(ln.dst), cert))
            else:
                self._log_opened(kind, zid, str(ln.dst), cert)

    def _log_opened(self, kind: str, zid: str, dst: str, cert: str) -> None:
        self.log.info("session opened: %s %s from %s%s", kind, zid, dst, cert)

    @staticmethod
    def snapshot(session) -> dict[str, Any]:
        """Sessions connected now: counts by kind and, per link, its remote end and the
        name in its certificate (TLS)."""
        kinds = {"client": 0, "peer": 0, "router": 0}
        by_zid: dict[str, str] = {}
        for t in session.info.transports():
            kind = str(t.whatami).rsplit(".", 1)[-1].lower()
            kinds[kind] = kinds.get(kind, 0) + 1
            by_zid[str(t.zid)] = kind
        listed = []
        for ln in session.info.links()[:MAX_LISTED]:
            listed.append({"zid": str(ln.zid), "kind": by_zid.get(str(ln.zid), "?"), "remote": ln.dst,
                           "local": ln.src, "certificate": ln.auth_identifier})
        return {"sessions": sum(kinds.values()), "sessions_by_kind": kinds, "links": listed}


def _open(r: RouterConfig, ctx):
    """Open the router session; a restarted router retries for a moment (its port may still
    be held), then the run fails with the engine's reason: restarting cannot cure a port
    taken by another program or a certificate that does not load."""
    end = time.monotonic() + (OPEN_RETRY_S if ctx.info.restart_count else 0.0)
    while True:
        try:
            return open_session(r)
        except ZenohOpenError as exc:
            if time.monotonic() >= end or not ctx.running:
                ctx.fail_run(str(exc))
                return None
            ctx.sleep(0.25)


def main(ctx) -> None:
    """The router stage: open the session, report its sessions on every heartbeat."""
    from .zenoh_log import EngineLog

    r: RouterConfig = ctx.cfg.router
    engine_log = EngineLog(ctx.log)
    engine_log.start()
    session = _open(r, ctx)
    if session is None:
        return
    table = SessionTable(ctx.log)
    # history: clients reconnecting to a restarted router may be in before the listeners
    listeners = [session.info.declare_transport_events_listener(table.on_transport, history=True),
                 session.info.declare_link_events_listener(table.on_link, history=True)]
    ctx.log.info("router %s listening on %s%s", session.info.zid(), ", ".join(r.listen),
                 f", connecting to {', '.join(r.connect)}" if r.connect else "")
    c = ctx.counters
    state: dict[str, Any] = {"snap": table.snapshot(session), "t": time.monotonic()}
    zid = str(session.info.zid())

    def report() -> None:
        now = time.monotonic()
        if not state.get("closed") and now - state["t"] >= 0.2:  # cheap, but not every 50 ms
            state["snap"], state["t"] = table.snapshot(session), now
        refused = engine_log.counts()
        c.extra.update(state["snap"], zid=zid, listen=list(r.listen),
                       sessions_opened=table.opened, sessions_closed=table.closed,
                       refused_connections=sum(refused.values()), rejected=refused,
                       last_refusal=engine_log.last_refusal)

    ctx.on_beat.append(report)
    try:
        while ctx.running:
            ctx.sleep(0.1)
    finally:
        state["t"] = 0.0
        report()
        state["closed"] = True  # the last heartbeat (on close) reports the counts, not the session
        for x in listeners:
            x.undeclare()
        session.close()


def router_line(st: dict) -> str:
    """One line: sessions now by kind, opened, closed, refused (with the last reason)."""
    k = st.get("sessions_by_kind", {})
    kinds = ", ".join(f"{n} {name}{'s' if n != 1 else ''}" for name, n in k.items() if n) or "none"
    refused = st.get("refused_connections", 0)
    why = f" (last: {st.get('last_refusal')})" if refused and st.get("last_refusal") else ""
    return (f"{st.get('sessions', 0)} session(s) connected ({kinds}); {st.get('sessions_opened', 0)} opened, "
            f"{st.get('sessions_closed', 0)} closed, {refused} refused{why}")


def router_summary(stats: dict) -> str:
    """The line ``pointflow router`` prints: the router stage's line, its restarts and uptime."""
    st = stats.get("stages", {}).get("router", {})
    who = f"router {st['zid']} on {', '.join(st.get('listen', []))}" if st.get("zid") else "router (starting)"
    return (f"{who}: {router_line(st)}; "
            f"restarts {st.get('restarts', 0)}, {stats.get('elapsed_s', 0):.1f} s")
