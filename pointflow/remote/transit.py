"""Points lost in transit, per source, from the ``link`` object of each chunk header.

The sender stamps every chunk of a source with ``{"epoch", "seq", "sent"}``: ``epoch`` is
fixed for one run of the sender, ``seq`` counts the source's data chunks (0, 1, 2...) and
``sent`` is the source's cumulative point count including this chunk. Every
``sync_every_s`` (and when it stops) it sends a sync: an empty chunk with
``{"epoch", "seq": <next seq>, "sent": <total>, "sync": true}``. A receiver then knows, for
each source, exactly how many points were sent up to the last message it got, so

    sent (since it joined) = received + lost_in_transit

holds at every sync. Messages arrive in order on one ZeroMQ connection; a gap in ``seq``
is a lost chunk and the gap in ``sent`` its points. A receiver that joins late (the first
message it sees has ``seq`` > 0) counts what was sent before as ``joined_after``, not
as lost.

A receiver with its own bounded queue in front of the decoder (the ``zenoh`` transport)
may drop a message that did arrive; it passes the dropped message's header to
:meth:`TransitLedger.observe` with ``dropped=True`` and the points count as
``receive_queue_full`` instead of received, so then

    sent (since it joined) = received + lost_in_transit + receive_queue_full
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ..chunk import ChunkError


@dataclass
class _Stream:
    epoch: str
    next_seq: int = 0
    sent: int = 0
    joined_after: int = 0
    received: int = 0
    lost_points: int = 0
    lost_chunks: int = 0
    dropped: int = 0


def _int(link: dict, key: str) -> int:
    v = link.get(key)
    if not isinstance(v, int) or isinstance(v, bool) or v < 0:
        raise ChunkError("bad_link", f"link.{key} must be a non-negative integer, got {v!r}")
    return v


class TransitLedger:
    """Per-source link bookkeeping of one receiver."""

    def __init__(self) -> None:
        self.streams: dict[str, _Stream] = {}
        #: Sources whose sender said it stopped (a sync with ``"end": true``).
        self.ended: set[str] = set()
        #: Totals of earlier epochs (a sender that restarted), per source.
        self._past: dict[str, dict[str, int]] = {}

    def observe(self, source: str, link: Any, n: int, dropped: bool = False) -> bool:
        """Account one message; True for a data chunk, False for a sync (deliver nothing).
        ``dropped``: the receiver got this message but dropped it before decoding (its queue
        was full): its points count as ``receive_queue_full``. Raises :class:`ChunkError`
        (``bad_link``, ``stale_link_seq``) for nonsense."""
        if not isinstance(link, dict) or not isinstance(link.get("epoch"), str):
            raise ChunkError("bad_link", f"link must be an object with a string epoch, got {link!r}")
        seq, sent = _int(link, "seq"), _int(link, "sent")
        sync = link.get("sync") is True
        if sync and n:
            raise ChunkError("bad_link", f"a sync message carries no points, this one has {n}")
        st = self.streams.get(source)
        if st is None or st.epoch != link["epoch"]:
            if st is not None:  # the sender restarted: keep the old epoch's totals
                past = self._past.setdefault(source, {})
                for k, v in self._stream_totals(st).items():
                    past[k] = past.get(k, 0) + v
            before = sent - (0 if sync else n)
            st = _Stream(epoch=link["epoch"], next_seq=seq, sent=before, joined_after=before if seq else 0)
            if seq == 0 and before:
                raise ChunkError("bad_link", f"first chunk (seq 0) says {before} points were sent before it")
            self.streams[source] = st
        if seq < st.next_seq:
            raise ChunkError("stale_link_seq", f"source {source!r}: link seq {seq} after {st.next_seq - 1}")
        gap = sent - (0 if sync else n) - st.sent
        if gap < 0:
            raise ChunkError("bad_link", f"source {source!r}: link.sent {sent} is below the {st.sent + n} already accounted")
        st.lost_chunks += seq - st.next_seq
        st.lost_points += gap
        st.sent = sent
        if sync:
            st.next_seq = seq
            if link.get("end") is True:
                self.ended.add(source)
            return False
        self.ended.discard(source)
        st.next_seq = seq + 1
        if dropped:
            st.dropped += n
            return False
        st.received += n
        return True

    @staticmethod
    def _stream_totals(st: _Stream) -> dict[str, int]:
        return {"sent": st.sent - st.joined_after, "received": st.received, "lost_points": st.lost_points,
                "lost_chunks": st.lost_chunks, "joined_after": st.joined_after, "dropped": st.dropped}

    def per_source(self) -> dict[str, dict[str, int]]:
        out: dict[str, dict[str, int]] = {}
        for src in set(self.streams) | set(self._past):
            tot = dict(self._past.get(src, {}))
            if src in self.streams:
                for k, v in self._stream_totals(self.streams[src]).items():
                    tot[k] = tot.get(k, 0) + v
            out[src] = tot
        return out

    def counters(self) -> dict[str, int]:
        """Flat numbers for stats: totals, and ``lost_in_transit:<source>`` per source."""
        per = self.per_source()
        out = {"link_sent": 0, "link_received": 0, "lost_in_transit": 0, "lost_chunks": 0, "joined_after": 0}
        for src, t in sorted(per.items()):
            out["link_sent"] += t.get("sent", 0)
            out["link_received"] += t.get("received", 0)
            out["lost_in_transit"] += t.get("lost_points", 0)
            out["lost_chunks"] += t.get("lost_chunks", 0)
            out["joined_after"] += t.get("joined_after", 0)
            out[f"lost_in_transit:{src}"] = t.get("lost_points", 0)
            out[f"link_sent:{src}"] = t.get("sent", 0)
            if t.get("dropped"):
                out["receive_queue_full"] = out.get("receive_queue_full", 0) + t["dropped"]
        return out
