"""The render stage's side of the handoff conversation with the cadence
(:mod:`pointflow.cadence.messages`): hello (a renderer that holds no slab, and its GPU),
frame done with its time, and idle when no handoff came for a while."""
from __future__ import annotations

import os
import time

import zmq

from ..ring.handoff import SlabReader
from .base import Renderer

__all__ = ["announce", "resync_if_idle", "feedback", "IDLE_RESYNC_S"]


def announce(sock, ctx, renderer: Renderer) -> None:
    """Tell the cadence a (new) renderer holds no slab, and what GPU it drives (the policy
    engine caps the budget by the adapter's storage limits and detects the tier from it)."""
    from ..cadence.messages import encode_hello

    gpu = None
    adapter = getattr(renderer, "adapter", None)
    if adapter is not None:
        try:
            from ..cadence.policy import gpu_info_from_adapter

            gpu = gpu_info_from_adapter(adapter)
        except Exception as exc:  # noqa: BLE001 - the policy then works from CPU and memory alone
            ctx.log.warning("could not describe the GPU adapter for the policy engine: %s", exc)
    try:
        sock.send_multipart(encode_hello(os.getpid(), ctx.info.restart_count, gpu=gpu), zmq.NOBLOCK)
    except zmq.Again:
        pass


#: A renderer that holds no slab and got no handoff for this long (or 4 cadence ticks, if
#: longer) tells the cadence so; a healthy cadence hands the next snapshot over within a tick.
IDLE_RESYNC_S = 0.5


def resync_if_idle(sock, reader: SlabReader, t_free: int, t_idle: int, tick_s: float) -> int:
    """Send ``idle`` (pointflow.cadence.messages) when no handoff came for a while: a
    cadence that froze and was replaced never read the releases queued to it and would
    otherwise wait for them forever. Returns when an idle message last went."""
    now = time.monotonic_ns()
    since = max(t_free, reader.t_last_ns, t_idle)
    limit = max(IDLE_RESYNC_S, 4 * tick_s)
    if reader.held is not None or (now - since) / 1e9 < limit:
        return t_idle
    from ..cadence.messages import encode_idle

    try:
        sock.send_multipart(encode_idle(reader.last_seq, (now - max(t_free, reader.t_last_ns)) / 1e6), zmq.NOBLOCK)
    except zmq.Again:
        pass
    return now


def feedback(sock, frame_ms: float, seq: int, drawn: bool = True) -> None:
    """Frame done (the cadence hands over the next snapshot now) and its time (the
    adaptive interval)."""
    try:
        from ..cadence.messages import encode_frame_time

        sock.send_multipart(encode_frame_time(frame_ms, seq, drawn), zmq.NOBLOCK)
    except (ImportError, zmq.Again):
        pass
