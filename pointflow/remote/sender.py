"""The sender stage of ``pointflow send``: the sources' chunks onto a network link.

``pointflow send CONFIG`` starts the config's sources as usual (each in its own source
process, any transport or plugin) but, instead of ingest, this stage: it binds the PULL
socket the sources push to, stamps each chunk with its per-source link sequence
(:mod:`.transit`), encodes it (optionally compressed and quantised, :mod:`.codec`) and
sends it on the link socket (PUB for fan-out, PUSH for one receiver) secured by
:mod:`.security`. It never makes a sensor wait: chunks go through a bounded queue that
drops its oldest chunk when the link cannot keep up (``link_queue_full``); a PUB socket
also drops at a slow subscriber's high-water mark. Either way the receivers see the gap
and count it as ``lost_in_transit``.

Accounting (``stats()["accounting"]`` of the send run)::

    points_in (from the sources) = points_out (handed to the link) + sum(drops[reason])
"""
from __future__ import annotations

import collections
import secrets
import time
from typing import Any

import numpy as np
import zmq

from .. import wire
from ..chunk import ChunkError, PointChunk
from ..codec import Compressor
from ..stage.context import take_messages
from .security import LinkSecurity

#: On stop, take the sources' last chunks until the PULL socket is quiet this long.
STOP_QUIET_S = 0.15
STOP_GRACE_S = 1.0
#: On stop, try this long to hand the queue and the final syncs to the link.
FLUSH_S = 2.0
#: On stop, wait at most this long for a link that carried data and is down (a heartbeat
#: dropped it; ZeroMQ is reconnecting) to have its peer again, so the final sync arrives.
RECONNECT_WAIT_S = 8.0


class LinkSender:
    """Stamps, encodes, queues and sends chunks on one link socket (no process of its own,
    so tests and the benchmark can drive it too)."""

    def __init__(self, sock: zmq.Socket, send_cfg, counters, log):
        self.sock = sock
        self.s = send_cfg
        self.counters = counters
        self.log = log
        self.epoch = secrets.token_hex(6)
        self.streams: dict[str, list[int]] = {}  # source -> [next seq, points sent]
        #: (frames, points, source) of data chunks, (frames, None, source) of syncs.
        self.queue: collections.deque[tuple[list[Any], int | None, str]] = collections.deque()
        self.compressor = Compressor(send_cfg.compression, send_cfg.compression_level, send_cfg.shuffle) \
            if send_cfg.compression != "none" else None
        self.resolution = send_cfg.quantise or None
        self.bytes_out = 0
        self.messages_out = 0
        self.syncs_out = 0
        self._empty = np.zeros((0, 3), np.float32)

    def add(self, chunk: PointChunk) -> None:
        n = chunk.n
        src = chunk.source_id or "source"
        st = self.streams.setdefault(src, [0, 0])
        link = {"epoch": self.epoch, "seq": st[0], "sent": st[1] + n}
        try:
            frames = wire.encode(chunk, link=link, compressor=self.compressor, resolution=self.resolution)
        except Exception as exc:  # noqa: BLE001 - a chunk that cannot be encoded is dropped, counted
            self.counters.drop("encode_error", n)
            self.log.warning("cannot encode a chunk of %s: %s", src, exc)
            return
        st[0] += 1
        st[1] += n
        self._enqueue(frames, n, src)

    def sync(self, end: bool = False) -> None:
        """Queue one sync per source (its totals so far). Syncs still queued are dropped
        first: the new ones supersede them, so a stalled link never piles them up."""
        if any(e[1] is None for e in self.queue):
            self.queue = collections.deque(e for e in self.queue if e[1] is not None)
        for src, (seq, sent) in self.streams.items():
            link = {"epoch": self.epoch, "seq": seq, "sent": sent, "sync": True}
            if end:
                link["end"] = True
            self.queue.append((wire.encode(PointChunk(positions=self._empty, source_id=src), link=link), None, src))

    def _enqueue(self, frames: list[Any], n: int, src: str) -> None:
        """Queue a data chunk; beyond ``queue_chunks`` data chunks the oldest is dropped
        (syncs do not count and are never dropped for data)."""
        self.queue.append((frames, n, src))
        data = sum(1 for e in self.queue if e[1] is not None)
        while data > self.s.queue_chunks:
            for i, (_, m, _s) in enumerate(self.queue):
                if m is not None:
                    del self.queue[i]
                    self.counters.drop("link_queue_full", m)
                    data -= 1
                    break

    def put(self, frames: list[Any], source: str) -> int | None:
        """Hand one message to the link without blocking: its bytes, or None if the link is
        full (the ZeroMQ socket here; :class:`pointflow.remote.zenoh_sender.ZenohLinkSender`
        publishes on Zenoh instead)."""
        try:
            self.sock.send_multipart(frames, zmq.NOBLOCK, copy=False)
        except zmq.Again:
            return None
        return sum(len(f) if isinstance(f, bytes) else f.nbytes for f in frames)

    def pump(self) -> bool:
        """Hand queued messages to the link without blocking; False if the link is full."""
        while self.queue:
            frames, n, src = self.queue[0]
            nbytes = self.put(frames, src)
            if nbytes is None:
                return False
            self.queue.popleft()
            self.messages_out += 1
            if n is None:
                self.syncs_out += 1
            else:
                self.counters.points_out += n
            self.bytes_out += nbytes
        return True

    @property
    def queued_points(self) -> int:
        return sum(e[1] for e in self.queue if e[1] is not None)

    @property
    def queued_chunks(self) -> int:
        return sum(1 for e in self.queue if e[1] is not None)

    def stats(self) -> dict[str, Any]:
        return {"link_bytes_out": self.bytes_out, "link_messages_out": self.messages_out,
                "link_syncs_out": self.syncs_out, "link_queue": len(self.queue),
                "link_epoch": self.epoch,
                **{f"link_sent:{k}": v[1] for k, v in self.streams.items()}}


def _wait_subscribers(ctx, sock, want: int, wait_s: float) -> int:
    """XPUB: wait (beating) until ``want`` subscriptions arrived or ``wait_s`` passed."""
    got = 0
    end = time.monotonic() + wait_s
    while got < want and ctx.running and time.monotonic() < end:
        if sock.poll(50, zmq.POLLIN):
            msg = sock.recv()
            got += bool(msg) and msg[0] == 1
        ctx.beat()
    if got < want and ctx.running:
        ctx.log.warning("only %d of %d subscriber(s) after %.1f s; sending anyway", got, want, wait_s)
    elif got >= want:
        ctx.log.info("%d subscriber(s) joined; sending", got)
    return got


def take_from_sources(ctx, pull, add, limit: int) -> int:
    """Up to ``limit`` chunks the local sources sent, each handed to ``add``; a malformed one
    is counted (``rejected_messages``) and logged. Both engines' senders take this way."""
    def one(frames) -> None:
        try:
            chunk = wire.decode(frames)
        except ChunkError as exc:  # a local source sent something broken: count it
            ctx.counters.extra["rejected_messages"] = ctx.counters.extra.get("rejected_messages", 0) + 1
            ctx.log.warning("dropped a malformed message from a source: %s", exc)
            return
        ctx.counters.points_in += chunk.n
        add(chunk)

    return take_messages(pull, one, limit)


def main(ctx) -> None:
    """Stage loop of the ZeroMQ engine (:mod:`.process` picks it)."""
    s = ctx.cfg.send
    pull = ctx.zmq.socket(zmq.PULL)
    pull.setsockopt(zmq.RCVHWM, 64)
    pull.setsockopt(zmq.LINGER, 0)
    pull.bind(ctx.endpoints.ingest)
    pub = s.socket == "pub"
    out = ctx.zmq.socket(zmq.XPUB if pub else zmq.PUSH)
    out.setsockopt(zmq.SNDHWM, s.send_hwm)
    out.setsockopt(zmq.LINGER, 1500)
    if s.send_buffer_kb:
        out.setsockopt(zmq.SNDBUF, s.send_buffer_kb * 1024)
    if pub:
        out.setsockopt(zmq.XPUB_VERBOSE, 1)
    link = LinkSecurity(ctx.zmq, s, s.bind, ctx.log, s.reconnect_initial_s, s.reconnect_max_s)
    link.apply(out)
    try:
        (out.bind if s.bind else out.connect)(s.endpoint)
    except zmq.ZMQError as exc:
        link.close()
        out.close(0)
        pull.close()
        raise RuntimeError(f"send: cannot {'bind' if s.bind else 'connect'} {s.endpoint}: {exc}") from None
    ctx.log.info("sending on %s (%s, %s, CURVE %s, compression %s, quantise %s)", s.endpoint,
                 "bind" if s.bind else "connect", s.socket, "on" if link.curve else "OFF", s.compression,
                 s.quantise or "off")
    snd = LinkSender(out, s, ctx.counters, ctx.log)
    subscriptions = 0

    def _stats() -> None:
        link.poll()
        ctx.counters.extra.update(snd.stats())
        ctx.counters.extra.update({f"link_{k}": v for k, v in link.counters.items()})
        ctx.counters.extra["link_subscriptions"] = subscriptions
        ctx.counters.extra["queued_points"] = snd.queued_points
        if link.refusal:
            ctx.counters.extra["link_refusal"] = link.refusal

    ctx.on_beat.append(_stats)

    def _take(limit: int) -> int:
        return take_from_sources(ctx, pull, snd.add, limit)

    try:
        if pub and s.wait_subscribers:
            subscriptions = _wait_subscribers(ctx, out, s.wait_subscribers, s.wait_s)
        next_sync = time.monotonic() + s.sync_every_s
        while ctx.running:
            ctx.beat()
            if pub:  # subscriptions (XPUB): count them, they need no answer
                while out.poll(0, zmq.POLLIN):
                    msg = out.recv()
                    subscriptions += bool(msg) and msg[0] == 1
            room = snd.pump()
            take = not s.backpressure or snd.queued_chunks < s.queue_chunks
            if take and pull.poll(0 if not room else 20, zmq.POLLIN):
                _take(64 if not s.backpressure else max(1, s.queue_chunks - snd.queued_chunks))
            if time.monotonic() >= next_sync:
                snd.sync()
                next_sync = time.monotonic() + s.sync_every_s
            snd.pump()
            if not room and snd.queue:
                out.poll(10, zmq.POLLOUT)
        # stopping: the sources were stopped first; take what they sent, then flush
        def drain() -> None:
            _take(256 if not s.backpressure else max(1, s.queue_chunks - snd.queued_chunks))
            if not snd.pump():
                out.poll(20, zmq.POLLOUT)

        ctx.drain_until_quiet(pull, drain, STOP_QUIET_S, STOP_GRACE_S)
        snd.sync(end=True)
        end = time.monotonic() + FLUSH_S
        while snd.queue and time.monotonic() < end:
            if not snd.pump():
                out.poll(20, zmq.POLLOUT)
            ctx.beat()
        if snd.queue:
            ctx.counters.drop("unsent_at_stop", snd.queued_points)
            ctx.log.warning("%d queued point(s) could not be sent before stopping", snd.queued_points)
            snd.queue.clear()
        else:
            hand_over_end(ctx, snd, link, out, RECONNECT_WAIT_S)
    finally:
        _stats()
        ctx.log.info("link closing: %d message(s), %d point(s) handed to the link; ZeroMQ lingers up to 1.5 s",
                     snd.messages_out, ctx.counters.points_out)
        link.close()
        out.close()  # lingers up to FLUSH_S for what ZeroMQ still holds
        pull.close()


def hand_over_end(ctx, snd: LinkSender, link: LinkSecurity, out: zmq.Socket, wait_s: float) -> bool:
    """Close only with a peer on the link: the final sync is handed to ZeroMQ, but a link that
    a heartbeat dropped a moment before is mid-reconnect, and the close's linger would drop
    the sync with the pipe. Wait (bounded) for the peer; if the link went down after the sync
    was handed over, hand it over again (a repeated sync changes nothing at the receiver).
    A link that never had a peer (a PUB nobody joined) is not waited for. True if the last
    hand-over had a peer."""
    link.poll()
    c = link.counters
    if not c["handshakes"]:
        return False
    handed = c["disconnects"]
    end = time.monotonic() + wait_s
    waited = False
    while time.monotonic() < end:
        link.poll()
        if c["peers"] > 0 and not snd.queue:
            if c["disconnects"] == handed:
                if waited:
                    ctx.log.info("link back before closing; the final sync was handed over again")
                return True
            snd.sync(end=True)  # the link went down since the last hand-over: again
            handed = c["disconnects"]
        if not waited and c["peers"] == 0:
            ctx.log.info("link down at stop; waiting up to %.0f s for its peer to hand over the final sync", wait_s)
            waited = True
        if not snd.pump():
            out.poll(20, zmq.POLLOUT)
        else:
            time.sleep(0.02)
        ctx.beat()
    ctx.log.warning("the link had no peer for %.0f s at stop: the final sync may not arrive", wait_s)
    return False


def send_summary(stats: dict) -> str:
    """One line for ``pointflow send``: points from the sources, sent, dropped, bytes."""
    st = stats.get("stages", {}).get("sender", {})
    pin, pout = st.get("points_in", 0), st.get("points_out", 0)
    drops = sum(st.get("drops", {}).values())
    b = st.get("link_bytes_out", 0)
    bpp = f"{b / pout:.2f} B/point" if pout else "-"
    peers = (f"zenoh publishers {st['link_publishers']}" if "link_publishers" in st else
             f"peers {st.get('link_peers', 0)}, refused {st.get('link_refused_handshakes', 0)}")
    if "link_publishers" not in st and pout and not st.get("link_handshakes", 0):
        # no receiver ever joined (none connected, or every one refused): ZeroMQ took the
        # points and dropped them, so "sent" and "on the link" would say what did not happen
        return (f"no receiver joined the link: {pout:,} of {pin:,} points ({b / 1e6:.1f} MB) were handed to "
                f"ZeroMQ and reached nobody ({drops:,} dropped before), {peers}, {stats.get('elapsed_s', 0):.1f} s")
    return (f"sent {pout:,} of {pin:,} points ({drops:,} dropped), {b / 1e6:.1f} MB on the link ({bpp}), "
            f"{peers}, {stats.get('elapsed_s', 0):.1f} s")
