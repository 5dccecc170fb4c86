"""The sender stage of ``pointflow send`` on the Zenoh engine (``send: {engine: zenoh}``).

The same stage as :mod:`.sender` (PULL from the sources, link sequence, encode, bounded
queue that drops its oldest chunk: ``link_queue_full``), but each source is published on
the Zenoh key ``<send.key>/<source>`` in the single-buffer framing of
:func:`pointflow.wire.to_single` (header as the attachment, data frames as the payload),
so plain, compressed and quantised chunks and the link header and syncs are the ZeroMQ
link's, byte for byte.

It never makes a sensor wait: live data is published with Zenoh's congestion control
``drop`` (a congested network queue drops the message instead of blocking the put; the
receivers see the gap in the link sequence and count it as ``lost_in_transit``). With
``backpressure: true`` (replays) it is ``block``: nothing is dropped, the replay waits.

Each source also holds a Zenoh liveliness token on its key, so receivers learn at once
when a sender dies or becomes unreachable (the token disappears), not only from missing
syncs.
"""
from __future__ import annotations

import time
from typing import Callable, Optional

import zmq

from .. import wire
from .options import source_key
from .sender import FLUSH_S, STOP_GRACE_S, STOP_QUIET_S, LinkSender, take_from_sources
from .zenoh_options import CONFIRM_PARAMETERS, ZenohOpenError, zenoh_config

#: A put to a full network queue waits this long (us) before Zenoh drops it (Zenoh's default
#: is 1 ms): rides out a busy host's scheduling hiccups, still never stalls for long.
SENDER_DEFAULTS = {"transport/link/tx/queue/congestion_control/drop/wait_before_drop": 10_000}
#: After the last put, before closing the session: Zenoh sends its batches asynchronously.
CLOSE_SETTLE_S = 0.3
#: How long the closing sender waits for its receivers to say they took its final sync
#: (:func:`confirm_delivery`): a replay (``backpressure``) waits for a slow viewer, live data
#: does not wait long.
CONFIRM_S = {True: 30.0, False: 2.0}


def open_sender_session(z):
    """:func:`.zenoh_options.open_session` with :data:`SENDER_DEFAULTS`."""
    import zenoh

    try:
        return zenoh.open(zenoh_config(z, SENDER_DEFAULTS))
    except zenoh.ZError as exc:
        where = ", ".join([f"listen {x}" for x in z.listen] + [f"connect {x}" for x in z.connect]) or "no endpoints"
        raise ZenohOpenError(f"zenoh session ({z.mode}; {where}) did not open: {exc}") from None


class ZenohLinkSender(LinkSender):
    """:class:`LinkSender` publishing on a Zenoh session: one publisher and one liveliness
    token per source, declared when its first chunk comes."""

    def __init__(self, session, send_cfg, counters, log):
        import zenoh

        super().__init__(None, send_cfg, counters, log)
        self.session = session
        self.prefix = send_cfg.key
        self.cc = zenoh.CongestionControl.BLOCK if send_cfg.backpressure else zenoh.CongestionControl.DROP
        self.publishers: dict[str, "zenoh.Publisher"] = {}
        self.tokens: dict[str, "zenoh.LivelinessToken"] = {}

    def _publisher(self, source: str):
        pub = self.publishers.get(source)
        if pub is None:
            key = source_key(self.prefix, source)
            # express off: Zenoh batches small messages; chunks are large anyway
            pub = self.session.declare_publisher(key, congestion_control=self.cc, express=False)
            self.publishers[source] = pub
            self.tokens[source] = self.session.liveliness().declare_token(key)
            self.log.info("publishing source %r on zenoh key %s", source, key)
        return pub

    def put(self, frames, source: str) -> int | None:
        header, body = wire.to_single(frames)
        self._publisher(source).put(body, attachment=header)
        return len(header) + len(body)

    def close(self) -> None:
        for t in self.tokens.values():
            t.undeclare()
        for p in self.publishers.values():
            p.undeclare()

    def stats(self) -> dict:
        return {**super().stats(), "link_publishers": len(self.publishers)}


def confirm_delivery(session, sources: dict[str, str], timeout: float, log,
                     matching: Optional[Callable[[str], bool]] = None) -> None:
    """Wait until the receivers of each source took its final sync, or ``timeout``.

    Closing a Zenoh session drops what its transmit queue still holds, and with a slow
    receiver (a replay with backpressure) that is the tail of the data and the final sync.
    Zenoh gives no delivery receipt, and a query may overtake earlier samples (callbacks run
    on several threads), so the sender asks each source's receivers, again and again, whether
    the source's end has been taken; each answers ``ended`` or ``pending``. No answer ends the
    wait at once only when no subscriber matches the key (``matching``: no receiver): a query
    can time out while a receiver is busy (its Zenoh thread held by a full queue), and closing
    then would drop what is still in transit. A matched receiver without the queryable (an
    older pointflow) keeps the sender waiting until ``timeout``."""
    import zenoh

    end = time.monotonic() + timeout
    pending = dict(sources)  # key -> source name
    answered: dict[str, int] = {}
    while pending and time.monotonic() < end:
        for key, name in list(pending.items()):
            try:
                replies = session.get(f"{key}?{CONFIRM_PARAMETERS}", payload=name.encode(),
                                      target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE,
                                      timeout=max(0.1, min(2.0, end - time.monotonic())))
                answers = [r.ok.payload.to_bytes() for r in replies if r.ok is not None]
            except zenoh.ZError as exc:
                log.warning("could not ask the receivers of %s whether they took everything: %s", key, exc)
                answers = []
            answered[key] = len(answers)
            if answers and all(a == b"ended" for a in answers):
                del pending[key]
            elif not answers and not (matching is not None and matching(key)):
                del pending[key]  # nobody to ask
        if pending:
            time.sleep(0.05)
    for key in sources:
        if key in pending:
            log.warning("a receiver of %s had not taken everything after %.0f s; what it had not is lost with the "
                        "session", key, timeout)
        elif answered.get(key):
            log.info("%d receiver(s) of %s took everything", answered[key], key)


def _matching(pub) -> bool:
    st = pub.matching_status  # a MatchingStatus object in eclipse-zenoh 1.x (the stub says bool)
    return bool(getattr(st, "matching", st))


def _wait_subscribers(ctx, snd: ZenohLinkSender, wait_s: float) -> bool:
    """Declare the configured sources' publishers and wait (beating) until each has a
    matching subscriber, or ``wait_s`` passed."""
    pubs = [snd._publisher(sc.name or f"source{i}") for i, sc in enumerate(ctx.cfg.sources)]
    end = time.monotonic() + wait_s
    while ctx.running and time.monotonic() < end and not all(_matching(p) for p in pubs):
        time.sleep(0.05)
        ctx.beat()
    ok = all(_matching(p) for p in pubs)
    if ok:
        ctx.log.info("every source has a subscriber; sending")
    elif ctx.running:
        ctx.log.warning("not every source has a subscriber after %.1f s; sending anyway", wait_s)
    return ok


def main(ctx) -> None:
    """Stage loop for ``send.engine: zenoh`` (chosen by :func:`pointflow.remote.process.main`)."""
    s = ctx.cfg.send
    z = s.zenoh
    pull = ctx.zmq.socket(zmq.PULL)
    pull.setsockopt(zmq.RCVHWM, 64)
    pull.setsockopt(zmq.LINGER, 0)
    pull.bind(ctx.endpoints.ingest)
    try:
        session = open_sender_session(z)
    except Exception as exc:  # noqa: BLE001 - ZenohOpenError or a missing package: one line
        pull.close()
        raise RuntimeError(f"send: {exc}") from None
    where = ", ".join([f"listen {x}" for x in z.listen] + [f"connect {x}" for x in z.connect])
    ctx.log.info("sending on zenoh %s/<source> (%s; %s; TLS %s; compression %s, quantise %s, congestion %s)", s.key,
                 z.mode, where or "no endpoints", "on" if z.tls else "OFF", s.compression, s.quantise or "off",
                 "block" if s.backpressure else "drop")
    snd = ZenohLinkSender(session, s, ctx.counters, ctx.log)

    def _stats() -> None:
        ctx.counters.extra.update(snd.stats())
        ctx.counters.extra["queued_points"] = snd.queued_points

    ctx.on_beat.append(_stats)

    def _add(chunk) -> None:
        snd.add(chunk)
        snd.pump()  # at once: a put never waits long (drop), so the queue only holds what block holds back

    def _take(limit: int) -> int:
        return take_from_sources(ctx, pull, _add, limit)

    try:
        if s.wait_subscribers:
            _wait_subscribers(ctx, snd, s.wait_s)
        next_sync = time.monotonic() + s.sync_every_s
        while ctx.running:
            ctx.beat()
            snd.pump()
            if pull.poll(20, zmq.POLLIN):
                _take(64 if not s.backpressure else max(1, s.queue_chunks - snd.queued_chunks))
            if time.monotonic() >= next_sync:
                snd.sync()
                next_sync = time.monotonic() + s.sync_every_s
            snd.pump()
        # stopping: the sources were stopped first; take what they sent, then flush
        ctx.drain_until_quiet(pull, lambda: (_take(256), snd.pump()), STOP_QUIET_S, STOP_GRACE_S)
        snd.sync(end=True)
        end = time.monotonic() + FLUSH_S
        while snd.queue and time.monotonic() < end:
            snd.pump()
            ctx.beat()
        if snd.queue:
            ctx.counters.drop("unsent_at_stop", snd.queued_points)
            ctx.log.warning("%d queued point(s) could not be sent before stopping", snd.queued_points)
            snd.queue.clear()
        pubs = {source_key(s.key, src): pub for src, pub in snd.publishers.items()}
        confirm_delivery(session, {source_key(s.key, src): src for src in snd.publishers}, CONFIRM_S[s.backpressure],
                         ctx.log, matching=lambda k: k in pubs and _matching(pubs[k]))
        time.sleep(CLOSE_SETTLE_S)
    finally:
        _stats()
        ctx.log.info("link closing: %d message(s), %d point(s) handed to zenoh", snd.messages_out,
                     ctx.counters.points_out)
        try:
            snd.close()
        finally:
            session.close()
            pull.close()
