"""Render → cadence control messages, sent on the *release* socket (render PUSH → cadence PULL).

They share the socket with the ring's slab releases (``pf.ring.release/1``) so they stay
ordered with them. Format: two frames ``[CONTROL_TAG, json]`` where json is one of

* ``{"type": "hello", "pid": int, "restart_count": int, "gpu": {...} | null}`` — the render
  stage (re)started and holds no slab; the cadence calls ``SlabWriter.reset_reader()`` and
  sends a full handoff next. ``gpu`` (optional; build it with
  :func:`pointflow.cadence.policy.gpu_info_from_adapter`) = ``{"name", "type" (wgpu
  adapter_type), "max_storage_binding", "max_buffer_size"}`` of the adapter the renderer uses:
  the policy engine re-resolves the tier and the GPU storage cap from it.
* ``{"type": "frame", "frame_ms": float, "seq": int, "drawn": bool}`` — the renderer finished
  the frame for handoff ``seq`` in ``frame_ms`` (wall time of the frame, GPU work included)
  and is ready for the next; feeds the adaptive cadence's frame-time EMA. ``drawn: false``
  (optional, default true): it took the handoff but drew nothing (nothing to frame yet, a
  rejected frame), so ``frame_ms`` says nothing about its speed.
* ``{"type": "idle", "last_seq": int, "idle_ms": float}`` — the renderer holds no slab and
  has had no handoff for ``idle_ms``; ``last_seq`` is the newest handoff it received. The
  cadence frees every slab it believes handed out that the renderer has seen (seq <=
  ``last_seq``) or that an earlier cadence handed out: releases sent to a cadence that
  froze and was replaced died with it, and without this the new cadence waited for them
  forever (``renderer_busy``).

The render side calls ``sock.send_multipart(encode_hello(...), zmq.NOBLOCK)`` etc.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Literal, Optional, Sequence, Union

from ..errors import Error

CONTROL_TAG = b"pf.cadence.ctl/1"


@dataclass(frozen=True)
class Hello:
    pid: int
    restart_count: int = 0
    gpu: Optional[dict] = None
    type: Literal["hello"] = "hello"


@dataclass(frozen=True)
class FrameTime:
    frame_ms: float
    seq: int = 0
    drawn: bool = True
    type: Literal["frame"] = "frame"


@dataclass(frozen=True)
class Idle:
    last_seq: int
    idle_ms: float = 0.0
    type: Literal["idle"] = "idle"


ControlMessage = Union[Hello, FrameTime, Idle]


class ControlMessageError(Error, ValueError):
    """A frame on the release socket carried the control tag but a bad body."""


def encode_hello(pid: int, restart_count: int = 0, gpu: Optional[dict] = None) -> list[bytes]:
    body = {"type": "hello", "pid": int(pid), "restart_count": int(restart_count), "gpu": gpu}
    return [CONTROL_TAG, json.dumps(body).encode()]


def encode_frame_time(frame_ms: float, seq: int = 0, drawn: bool = True) -> list[bytes]:
    body = {"type": "frame", "frame_ms": float(frame_ms), "seq": int(seq), "drawn": bool(drawn)}
    return [CONTROL_TAG, json.dumps(body).encode()]


def encode_idle(last_seq: int, idle_ms: float) -> list[bytes]:
    return [CONTROL_TAG, json.dumps({"type": "idle", "last_seq": int(last_seq), "idle_ms": float(idle_ms)}).encode()]


def is_control(frames: Sequence[bytes]) -> bool:
    return len(frames) >= 1 and bytes(frames[0]) == CONTROL_TAG


def decode_control(frames: Sequence[bytes]) -> Optional[ControlMessage]:
    """The message, or ``None`` when ``frames`` is not a control message (e.g. a release).

    Raises :class:`ControlMessageError` (naming what is wrong) for a malformed one."""
    if not is_control(frames):
        return None
    if len(frames) != 2:
        raise ControlMessageError(f"cadence control message: expected 2 frames, got {len(frames)}")
    try:
        d = json.loads(bytes(frames[1]))
    except (ValueError, UnicodeDecodeError) as exc:
        raise ControlMessageError(f"cadence control message: body is not JSON ({exc})") from None
    if not isinstance(d, dict):
        raise ControlMessageError("cadence control message: body must be a JSON object")
    kind = d.get("type")
    try:
        if kind == "hello":
            gpu = d.get("gpu")
            if gpu is not None and not isinstance(gpu, dict):
                raise ControlMessageError(f"cadence control message 'hello': gpu must be an object, got {gpu!r}")
            return Hello(pid=int(d["pid"]), restart_count=int(d.get("restart_count", 0)), gpu=gpu)
        if kind == "frame":
            ms = float(d["frame_ms"])
            if not math.isfinite(ms) or ms < 0:
                raise ControlMessageError(f"cadence control message: frame_ms must be finite and >= 0, got {ms!r}")
            return FrameTime(frame_ms=ms, seq=int(d.get("seq", 0)), drawn=bool(d.get("drawn", True)))
        if kind == "idle":
            return Idle(last_seq=int(d["last_seq"]), idle_ms=float(d.get("idle_ms", 0.0)))
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, ControlMessageError):
            raise
        raise ControlMessageError(f"cadence control message {kind!r}: missing or bad field ({exc})") from None
    raise ControlMessageError(f"cadence control message: unknown type {kind!r}")
