"""Steering a replay (``file``, ``rosbag``): pause, resume, seek, step, rate, loop.

A replaying transport owns a :class:`PlaybackClock`. It asks the clock before each message
(``yield from clock.pace(t)``, t = the message's time in seconds from the start of the
recording) and tells it what went out (``clock.released(t, index)``); between messages
it checks ``clock.seek_pending`` and, when set, starts again from ``clock.take_seek()``.
The source stage serves the control path: a REP socket bound at
:func:`playback_endpoint` (one per source, in the run directory), one JSON request per
message, the reply the clock's state (docs/api.md, "Steer the replay")::

    {"cmd": "playback", "paused": true}                 pause (false: resume)
    {"cmd": "playback", "seek_s": 12.5}                 seek to a time (s from the start)
    {"cmd": "playback", "seek_fraction": 0.5}           seek to a fraction of the length
    {"cmd": "playback", "step": 1}                      release one message (pauses first)
    {"cmd": "playback", "rate": 2.0}                    twice as fast as recorded
    {"cmd": "playback", "loop": true}                   start again at the end
    {"cmd": "playback", "hold": true}                   at the end, wait for a seek (do not end)
    {"cmd": "playback"}                                 the state only

A seek lands on the first message whose time is at or after the target; while paused, that
message goes once (a view shows where the seek landed) and the replay stays paused.
``seeks_landed`` reaches ``seeks`` once that message went out or the end is reached, so a
caller can wait for it (``Pipeline.playback`` does); ``next_s`` is the message waiting to go.
The ring keeps
what it holds (the points from before the seek stay until newer points evict them);
``seeks`` counts seeks and ``skipped_messages`` the messages a forward seek passed over.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from typing import Any, Iterator, Optional, Union

from ..errors import KeyedError
from ..stage.endpoints import Endpoint
from ..typed import ConfigError

__all__ = ["PlaybackClock", "PlaybackConfig", "PlaybackError", "playback_endpoint", "check_playback"]

#: Longest single sleep while waiting (the stage beats and serves commands in between).
_SLICE_S = 0.02


#: Replay control of the sources that read recordings (REP bound by each; ``-<index>`` is
#: added per source, or the index to a tcp port).
ENDPOINTS = (Endpoint("playback", "playback", "replay control (REP bound by each replaying source)"),)


class PlaybackError(KeyedError):
    """A playback request that cannot be applied; ``key`` names the argument."""

    @staticmethod
    def _text(key: str, message: str) -> str:
        return f"{key}: {message}"


@dataclasses.dataclass
class PlaybackConfig:
    """The ``playback:`` block (and ``pointflow run --start/--rate/--loop``): how every
    replaying source starts. null = each transport's own option."""

    #: Where to start: seconds from the start of the recording, or a fraction as "50%".
    start: Union[float, str] = 0.0
    #: Speed factor on the recorded timing (2 = twice as fast).
    rate: Optional[float] = None
    loop: Optional[bool] = None
    #: Start paused (step or resume from Python).
    paused: bool = False
    #: At the end of a replay (no loop), keep the source waiting for a seek instead of ending it.
    hold: bool = False


#: Replay rates taken (times as fast as recorded): 1000x replays an hour in 3.6 s; at 0.001x
#: a second of recording takes 17 minutes. Beyond, a rate is a typo or an attack (1e-300
#: would stall the replay for ever, 1e9 is "as fast as possible": ``realtime: false``).
RATE_RANGE = (0.001, 1000.0)


def check_playback(p: PlaybackConfig, path: str = "playback") -> None:
    if isinstance(p.start, str):
        s = p.start.strip()
        try:
            f = float(s[:-1]) / 100.0 if s.endswith("%") else float(s)
        except ValueError:
            raise ConfigError(f"{path}.start", f"must be seconds or a percentage like '25%', got {p.start!r}") from None
        if not s.endswith("%"):
            p.start = f
        elif not 0.0 <= f <= 1.0:
            raise ConfigError(f"{path}.start", f"a percentage must be within 0%..100%, got {p.start!r}")
    if not isinstance(p.start, str) and not (math.isfinite(p.start) and p.start >= 0):
        raise ConfigError(f"{path}.start", f"must be >= 0 seconds, got {p.start!r}")
    if p.rate is not None and not (math.isfinite(p.rate) and RATE_RANGE[0] <= p.rate <= RATE_RANGE[1]):
        raise ConfigError(f"{path}.rate", f"must be within {RATE_RANGE[0]:g}..{RATE_RANGE[1]:g} (times as fast as "
                          f"recorded), got {p.rate!r}")


def playback_endpoint(base: str, index: int) -> str:
    """Source ``index``'s control endpoint from ``endpoints.playback`` (ipc: a file per
    source beside it; tcp: the port plus the index)."""
    if base.startswith("tcp://"):
        host, _, port = base[len("tcp://"):].rpartition(":")
        return f"tcp://{host}:{int(port) + index}"
    stem = base[:-len(".sock")] if base.endswith(".sock") else base
    return f"{stem}-{index}.sock"


class PlaybackClock:
    """When each message of a replay may go, and the state a control request changes."""

    def __init__(self, *, rate: float = 1.0, loop: bool = False, realtime: bool = True):
        #: Speed factor; ``realtime`` False = as fast as ingest takes (pause and step still hold).
        self.rate = float(rate)
        self.loop = bool(loop)
        self.realtime = bool(realtime)
        self.paused = False
        self.hold = False
        self.at_end = False
        #: The recording's length in seconds, when the transport knows it (seek checks, fractions).
        self.duration_s: Optional[float] = None
        #: Number of messages in one pass, when known.
        self.messages: Optional[int] = None
        self.position_s = 0.0  # time of the last message released
        self.index = -1  # index of the last message released (in the recording, from 0)
        self.seeks = 0
        #: Seeks the replay has reached (:meth:`landed`): ``seeks_landed == seeks`` once the
        #: last seek's message went out (playing), waits to go (paused) or the end was reached.
        self.seeks_landed = 0
        #: Time of the message waiting to go (paused: the one a step or resume sends); None
        #: while none waits.
        self.next_s: Optional[float] = None
        self.steps_done = 0
        self.skipped_messages = 0
        self._steps = 0
        self._seek: Optional[float] = None
        self._show_once = False  # a seek while paused: release the message it lands on
        self._anchor: Optional[tuple[float, float]] = None  # (media time, wall time) it maps to
        #: The anchor's media time runs on across loops: a pass's time t is ``t + _base_s`` on it
        #: (:meth:`restart` with the pass's length adds it up), so a loop keeps the schedule.
        self._base_s = 0.0
        self._released_s = 0.0  # the last message released, on that running media time
        self._start: Union[float, str] = 0.0

    # ----------------------------------------------------------------- set-up
    def configure(self, cfg: Optional[PlaybackConfig]) -> None:
        """The pipeline's ``playback:`` block (CLI flags) over the transport's own options."""
        if cfg is None:
            return
        if cfg.rate is not None:
            self.rate = float(cfg.rate)
            self.realtime = True
        if cfg.loop is not None:
            self.loop = bool(cfg.loop)
        self.paused = bool(cfg.paused)
        self.hold = bool(cfg.hold)
        self._start = cfg.start

    def start_s(self) -> float:
        """Where the first pass starts (a percentage needs the length)."""
        s = self._start
        if isinstance(s, str):
            f = float(s.strip()[:-1]) / 100.0
            if self.duration_s is None:
                logging.getLogger("pointflow.playback").warning(
                    "playback.start %s: the recording's length is not known before its first pass (a stream of a "
                    "non-LAS file); starting at the beginning (give start in seconds instead)", s)
                return 0.0
            return f * self.duration_s
        if self.duration_s is not None and s > self.duration_s:
            logging.getLogger("pointflow.playback").warning(
                "playback.start %g s is past the end of the recording (%g s): nothing to replay", s, self.duration_s)
        return float(s)

    # ----------------------------------------------------------------- pacing
    @property
    def seek_pending(self) -> bool:
        return self._seek is not None

    def take_seek(self) -> Optional[float]:
        s, self._seek = self._seek, None
        if s is not None:
            self._anchor = None
            self.next_s = None
            # paused: the message at the sought position goes once, so a view shows where the
            # seek landed (a timeline dragged while paused); the replay stays paused after it
            self._show_once = self.paused
        return s

    def _land(self) -> None:
        """The replay reached the last seek's target: every seek asked for so far has landed."""
        if self._seek is None:
            self.seeks_landed = self.seeks

    def restart(self, pass_s: Optional[float] = None) -> None:
        """A new pass (loop). Without ``pass_s``: the next message goes at once. With it (the
        length of the pass that ended, in seconds of recording: ``files / rate`` for scans)
        the schedule goes on: the next pass's time 0 is due ``pass_s`` (over ``rate``) after the
        last pass's, i.e. one period after its last scan, however many messages a pass has
        (one included). A replay already behind that (held back by ingest) starts the pass at
        once instead of rushing messages out to catch up."""
        if pass_s is None or self._anchor is None or self.rate <= 0:
            self._anchor = None
            return
        t0, w0 = self._anchor
        due = w0 + (self._base_s + pass_s - t0) / self.rate
        self._base_s += pass_s
        if due < time.monotonic():
            self._anchor = None

    def pace(self, t_s: float, *, counts: bool = True) -> Iterator[None]:
        """Yield None while the message at ``t_s`` must wait (paused, or not yet due); return
        when it may go, or when a seek is pending (the caller checks ``seek_pending``).
        ``counts``: the message is one a step releases (False: transforms riding along)."""
        self.next_s = float(t_s)
        while True:
            if self._seek is not None:
                return
            if self.paused:
                if self._show_once and counts:
                    self._show_once = False
                    self._anchor = (t_s + self._base_s, time.monotonic())
                    return
                if self.seeks_landed < self.seeks and self._steps == 0:
                    self._land()  # paused on the sought message (a transform): it waits to go (next_s)
                if self._steps > 0:
                    if counts:
                        self._steps -= 1
                        self.steps_done += 1
                    self._anchor = (t_s + self._base_s, time.monotonic())
                    return
                time.sleep(_SLICE_S)
                yield None
                continue
            if not self.realtime or self.rate <= 0:
                return
            now = time.monotonic()
            if self._anchor is None:
                self._anchor = (t_s + self._base_s, now)
                return
            t0, w0 = self._anchor
            left = w0 + (t_s + self._base_s - t0) / self.rate - now
            if left <= 0:
                return
            time.sleep(min(left, _SLICE_S))
            if left > _SLICE_S:
                yield None

    def hold_at_end(self) -> Iterator[None]:
        """At the end of a pass without loop: with ``hold``, wait until a seek (or loop) asks
        for more; the caller then goes on, else the replay ends."""
        self.at_end = True
        self.next_s = None
        self._land()  # a seek past the last message lands at the end
        while self.hold and self._seek is None and not self.loop:
            time.sleep(_SLICE_S)
            yield None
        self.at_end = False

    def released(self, t_s: float, index: int) -> None:
        self.position_s = float(t_s)
        self._released_s = self.position_s + self._base_s
        self.index = int(index)
        self.next_s = None
        if self.seeks_landed < self.seeks:
            self._land()  # playing: the sought message went out

    # ----------------------------------------------------------------- control
    def command(self, msg: Any) -> dict:
        """Apply one request (see the module docstring); returns the state."""
        if not isinstance(msg, dict) or msg.get("cmd") != "playback":
            raise PlaybackError("cmd", f"expected {{'cmd': 'playback', ...}}, got {msg!r}")
        allowed = ("paused", "seek_s", "seek_fraction", "step", "rate", "loop", "hold")
        for k in msg:
            if k != "cmd" and k not in allowed:
                raise PlaybackError(k, f"unknown argument; playback takes {', '.join(allowed)}")
        if "seek_s" in msg and "seek_fraction" in msg:
            raise PlaybackError("seek_s", "give seek_s or seek_fraction, not both")
        # check everything before changing anything
        rate = _number(msg["rate"], "rate", lo=RATE_RANGE[0], hi=RATE_RANGE[1]) if "rate" in msg else None
        seek = None
        if "seek_s" in msg:
            seek = _number(msg["seek_s"], "seek_s", lo=0.0)
            if self.duration_s is not None and seek > self.duration_s:
                raise PlaybackError("seek_s", f"{seek:g} s is past the end of the recording ({self.duration_s:g} s)")
        if "seek_fraction" in msg:
            f = _number(msg["seek_fraction"], "seek_fraction", lo=0.0, hi=1.0)
            if self.duration_s is None:
                raise PlaybackError("seek_fraction", "the recording's length is not known yet (a stream of a "
                                    "non-LAS file is counted in its first pass); seek by seek_s")
            seek = f * self.duration_s
        step = 0
        if "step" in msg:
            s = msg["step"]
            if isinstance(s, bool) or not isinstance(s, int) or s < 0:
                raise PlaybackError("step", f"expected a whole number of messages >= 0, got {s!r}")
            step = s
        for k in ("paused", "loop", "hold"):
            if k in msg and not isinstance(msg[k], bool):
                raise PlaybackError(k, f"expected true or false, got {msg[k]!r}")
        if rate is not None:
            if self._anchor is not None:  # keep the time already waited: re-anchor at the last message
                t0, w0 = self._anchor
                self._anchor = (self._released_s, w0 + (self._released_s - t0) / self.rate)
            self.rate = rate
            self.realtime = True
        if "loop" in msg:
            self.loop = msg["loop"]
        if "hold" in msg:
            self.hold = msg["hold"]
        if "paused" in msg:
            if self.paused and not msg["paused"]:
                self._anchor = None  # resume: the next message goes now
            self.paused = msg["paused"]
        if step:
            self.paused = True
            self._steps += step
        if seek is not None:
            self._seek = seek
            self.seeks += 1
        return self.state()

    def state(self) -> dict:
        return {"paused": self.paused, "rate": self.rate if self.realtime else 0.0, "loop": self.loop,
                "hold": self.hold, "at_end": self.at_end,
                "position_s": round(self.position_s, 6), "index": self.index, "duration_s": self.duration_s,
                "messages": self.messages, "seeks": self.seeks, "seeks_landed": self.seeks_landed,
                "next_s": None if self.next_s is None else round(self.next_s, 6), "steps": self.steps_done,
                "skipped_messages": self.skipped_messages, "seek_pending": self._seek is not None,
                "steps_pending": self._steps}

    def counters(self) -> dict:
        """Numbers for the source's stats (``transport_playback_*``)."""
        return {"playback_position_s": round(self.position_s, 6), "playback_index": self.index,
                "playback_paused": int(self.paused), "playback_rate": self.rate if self.realtime else 0.0,
                "playback_seeks": self.seeks, "playback_steps": self.steps_done,
                "playback_skipped_messages": self.skipped_messages}


def _number(v: Any, key: str, lo: float = -math.inf, hi: float = math.inf, lo_open: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise PlaybackError(key, f"expected a number, got {repr(v)[:60]}")
    try:
        x = float(v)
    except OverflowError:  # a JSON integer of hundreds of digits
        x = math.inf
    if not math.isfinite(x) or x < lo or x > hi or (lo_open and x == lo):
        rng = f"{'>' if lo_open else '>='} {lo:g}" + (f" and <= {hi:g}" if hi != math.inf else "")
        raise PlaybackError(key, f"expected a finite number {rng}, got {repr(v)[:60]}")
    return x


def serve(sock, clock: PlaybackClock, log, counters) -> None:
    """Answer the pending requests on the source's REP socket (never raises)."""
    import zmq

    while sock.poll(0, zmq.POLLIN):
        try:
            rep = {"state": clock.command(json.loads(sock.recv()))}
        except PlaybackError as exc:
            counters.extra["playback_refused"] = counters.extra.get("playback_refused", 0) + 1
            log.debug("playback request refused: %s", exc)  # the caller raises it: said once, there
            rep = {"error": str(exc), "key": exc.key, "message": exc.message}
        except Exception as exc:  # noqa: BLE001 - a bad request must not end the replay
            rep = {"error": f"{type(exc).__name__}: {exc}", "key": "cmd"}
        sock.send_string(json.dumps(rep))


def request(zctx, endpoint: str, msg: dict, timeout_s: float = 5.0) -> dict:
    """One request to a source's playback socket (the caller's side)."""
    import zmq

    sock = zctx.socket(zmq.REQ)
    sock.setsockopt(zmq.LINGER, 0)
    try:
        sock.connect(endpoint)
        sock.send_string(json.dumps(msg))
        if not sock.poll(int(timeout_s * 1000)):
            raise TimeoutError(f"no answer from {endpoint} within {timeout_s} s (has the replay ended?)")
        return json.loads(sock.recv())
    finally:
        sock.close(0)
