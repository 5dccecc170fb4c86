"""Ingest's side of the recording: hand each chunk ingest pushes into the ring to the
recorder stage without ever waiting (a PUSH socket with a bounded high-water mark, sent
with ``NOBLOCK``; a copy that would block is dropped and counted as ``record_dropped``).

Counters (in ingest's stats)::

    record_offered = record_sent + record_dropped          (points)

With ``frames.fixed`` set, ingest also offers each transforms message it accepts
(:meth:`RecordTap.offer_transforms`: the ``pointflow.transforms/1`` JSON, one frame, on the
same socket, in order with the chunks); one that would block is dropped and counted as
``record_transforms_dropped`` (transforms, not points, so the balance above stays exact).
"""
from __future__ import annotations

import zmq

from .. import wire
from ..frames import message as transforms


class RecordTap:
    def __init__(self, zctx: zmq.Context, endpoint: str, hwm: int, channels=None, exclude=()):
        self.sock = zctx.socket(zmq.PUSH)
        self.sock.setsockopt(zmq.SNDHWM, hwm)
        self.sock.setsockopt(zmq.LINGER, 2000)  # on stop, what is queued still reaches the recorder
        self.sock.connect(endpoint)
        self.keep = set(channels) if channels is not None else None
        # source_index marks a point's source for per-source visibility (render/view/protocol.py): not data
        self.exclude = set(exclude) | {"source_index"}
        self.offered = self.sent = self.dropped = 0
        self.messages_sent = 0
        self.tf_sent = self.tf_dropped = 0

    def chans(self, chans: dict) -> dict:
        """The channels of a chunk that go into the recording."""
        if self.keep is None and not self.exclude:
            return chans
        return {k: v for k, v in chans.items()
                if k not in self.exclude and (self.keep is None or k in self.keep)}

    def offer(self, chunk) -> None:
        n = chunk.n
        self.offered += n
        try:
            self.sock.send_multipart(wire.encode(chunk), zmq.NOBLOCK, copy=False)
        except zmq.Again:
            self.dropped += n
            return
        self.sent += n
        self.messages_sent += 1

    def offer_transforms(self, batch: transforms.Transforms) -> None:
        """A transforms batch ingest accepted, for /tf and /tf_static in the recording."""
        n = len(batch)
        try:
            self.sock.send_multipart(transforms.encode(batch), zmq.NOBLOCK)
        except zmq.Again:
            self.tf_dropped += n
            return
        self.tf_sent += n

    def stats(self) -> dict:
        out = {"record_offered": self.offered, "record_sent": self.sent, "record_dropped": self.dropped,
               "record_messages_sent": self.messages_sent}
        if self.tf_sent or self.tf_dropped:
            out.update(record_transforms_sent=self.tf_sent, record_transforms_dropped=self.tf_dropped)
        return out

    def close(self) -> None:
        self.sock.close()
