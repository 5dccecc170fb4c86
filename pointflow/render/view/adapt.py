"""Frames that fit the link: while a view moves over a slow link its frames get smaller
(lower JPEG quality, then half or quarter size, upscaled by the page); when the camera rests
the still goes lossless and full size, as before (docs/views.md, "Over a slow link").

Two parts:

* :func:`decide` — the policy, a pure function of what was observed (frames/s shown,
  how much of the time the view waited on the link, the link's estimated rate, the bytes
  each level is expected to take) to a :class:`Level` of :data:`LEVELS`;
* :class:`Link` — one client's observations, fed by the view server: when each frame
  started to be written, when the page acknowledged it (acks come in order), and whether
  both frames of credit were out (the view waited on the link or the page, not on render).

Why these signals: a frame rate under target is the link's fault only when the view was
starved of credit (its frames were all out, waiting to be acknowledged); a render stage
that is simply slow leaves credit unused, and lowering the quality would not help it, so
the level stays. The link's rate is measured on frames sent back to back (the next frame
was written before the previous one was acknowledged): bytes over the interval between the
two acks. With two frames of credit and a round trip, that underestimates a link the view
does not fill, which only keeps a level, never raises it wrongly. The policy is pure and
its inputs are plain numbers, so it is tested without a link (tests/serve/test_adapt.py).
"""
from __future__ import annotations

import collections
import time
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np

from .encode import Encoded, encode_jpeg, encode_png

__all__ = ["Level", "LEVELS", "Observed", "decide", "Link", "encode_level", "STILL"]


@dataclass(frozen=True)
class Level:
    """How a frame is sent: ``reduce`` (1, 2, 4: the picture's side divided by it) and the
    JPEG ``quality`` (0 = the configured one); ``lossless`` for the still (PNG, full size)."""

    reduce: int
    quality: int
    lossless: bool = False


#: The ladder while moving, best first. Level 0 is the configured JPEG quality at full size.
LEVELS: tuple[Level, ...] = (Level(1, 0), Level(1, 60), Level(2, 80), Level(2, 60), Level(2, 40), Level(4, 60))
#: Expected bytes of each level relative to level 0, before any was seen (a 1280x720 point
#: cloud frame, bench/bench_link.py); replaced by what each level really takes.
PRIOR = (1.0, 0.68, 0.33, 0.24, 0.17, 0.08)
#: The still: lossless, full size.
STILL = Level(1, 0, lossless=True)
#: The link's rate is planned for this share of it (the rest absorbs jitter and texts).
HEADROOM = 0.8
#: Going back up a level needs this much more room than going down (no see-saw).
HYSTERESIS = 0.75
#: A view counts as starved when its credit was all out for more than this share of the time.
STARVED = 0.5
#: Observations older than this are forgotten (frames/s, starvation, link rate).
WINDOW_S = 2.0
#: After a change of level, wait this long (and for MIN_FRAMES) before judging it.
SETTLE_S = 0.5
MIN_FRAMES = 4


@dataclass(frozen=True)
class Observed:
    """What :func:`decide` looks at."""

    level: int  #: the level now
    fps: Optional[float]  #: frames shown per second lately (None: too few to say)
    starved: float  #: share of the time the view's credit was all out (0..1)
    link_bps: Optional[float]  #: the link's estimated rate in bit/s (None: not measured)
    expected_bytes: Sequence[float]  #: bytes a frame is expected to take at each level
    target_fps: float  #: frames/s to keep while moving


def _budget(o: Observed) -> Optional[float]:
    if o.link_bps is None or o.target_fps <= 0:
        return None
    return o.link_bps / 8.0 / o.target_fps * HEADROOM


def decide(o: Observed) -> int:
    """The level for the next moving frames: down (to the best level whose frames fit the
    link at the target rate, at least one step) when the view shows fewer frames than the
    target and waited on the link (its credit was out: the frames were on the link or in
    the page; with two frames a round trip, a smaller frame is a shorter trip, so this holds
    on a link of ample rate but long delay too); up one step when it keeps the target and the better
    level fits with room to spare; else the same."""
    n = len(LEVELS)
    level = min(max(o.level, 0), n - 1)
    if o.target_fps <= 0 or o.fps is None:
        return level
    budget = _budget(o)
    if o.fps < o.target_fps and o.starved > STARVED:
        if level == n - 1:
            return level
        if budget is not None:
            for k in range(level + 1, n):
                if o.expected_bytes[k] <= budget:
                    return k
            return n - 1
        return level + 1
    if o.fps >= o.target_fps and level > 0:
        if budget is not None and o.expected_bytes[level - 1] <= budget * HYSTERESIS:
            return level - 1
        if budget is None and o.starved < STARVED / 2:  # nothing measured, nothing waited: try better
            return level - 1
    return level


@dataclass
class _Sent:
    t_start: float
    nbytes: int
    moving: bool


@dataclass
class Link:
    """One client's link, as the view server sees it (module docstring)."""

    target_fps: float = 20.0
    level: int = 0
    t_level: float = 0.0
    #: frames written and not yet acknowledged, oldest first
    pending: collections.deque = field(default_factory=collections.deque)
    #: (t, bytes, moving) of acknowledged frames; (t, bit/s) link samples
    acks: collections.deque = field(default_factory=lambda: collections.deque(maxlen=256))
    samples: collections.deque = field(default_factory=lambda: collections.deque(maxlen=256))
    #: bytes per pixel of each level (an average of what it took), None until seen
    bpp: list = field(default_factory=lambda: [None] * len(LEVELS))
    #: time at full credit out, integrated: (since, state) and (t, seconds starved) marks
    _full: bool = False
    _t_full: float = 0.0
    starved_marks: collections.deque = field(default_factory=lambda: collections.deque(maxlen=512))
    t_ack: float = 0.0
    changes: int = 0

    # ---------------------------------------------------------------- feeding
    def flight(self, full: bool, now: float) -> None:
        """Whether every frame of credit is out now (called when that may have changed)."""
        if full != self._full:
            if self._full:
                self.starved_marks.append((self._t_full, now))
            self._full, self._t_full = full, now

    def sent(self, nbytes: int, moving: bool, t_start: float) -> None:
        """A frame started to be written (``t_start``)."""
        self.pending.append(_Sent(t_start, nbytes, moving))

    def acked(self, now: float) -> None:
        """The page acknowledged its oldest frame. A rate sample: when the frame was written
        before the previous one was acknowledged (back to back), bytes over the interval
        between the two acks; else bytes over its whole trip (a lower bound: the round trip
        is in it)."""
        if not self.pending:
            return
        s = self.pending.popleft()
        if self.t_ack and s.t_start < self.t_ack and now > self.t_ack:
            self.samples.append((now, s.nbytes * 8.0 / (now - self.t_ack)))
        elif now > s.t_start:
            self.samples.append((now, s.nbytes * 8.0 / (now - s.t_start)))
        self.acks.append((now, s.nbytes, s.moving))
        self.t_ack = now

    def encoded(self, level: int, nbytes: int, pixels: int) -> None:
        """What a moving frame at ``level`` took (``pixels``: the view's, before reduction)."""
        if pixels <= 0 or not 0 <= level < len(LEVELS):
            return
        b = nbytes / pixels
        old = self.bpp[level]
        self.bpp[level] = b if old is None else 0.7 * old + 0.3 * b

    # ---------------------------------------------------------------- reading
    def link_bps(self, now: float) -> Optional[float]:
        """The link's rate: the highest sample lately (a sample underestimates when the link
        idled between the two acks; it does not overestimate)."""
        recent = [r for t, r in self.samples if now - t <= WINDOW_S]
        return max(recent) if recent else None

    def fps(self, now: float) -> Optional[float]:
        """Moving frames shown per second since the level was last changed (within WINDOW_S)."""
        since = max(self.t_level, now - WINDOW_S)
        ts = [t for t, _, moving in self.acks if t >= since and moving]
        if now - since < SETTLE_S or len(ts) < MIN_FRAMES:
            return None
        return len(ts) / (now - since)

    def starved(self, now: float) -> float:
        since = max(self.t_level, now - WINDOW_S)
        if now <= since:
            return 0.0
        total = sum(max(0.0, b - max(a, since)) for a, b in self.starved_marks if b > since)
        if self._full:
            total += now - max(self._t_full, since)
        return min(1.0, total / (now - since))

    def expected_bytes(self, pixels: int) -> list[float]:
        """Bytes a frame of ``pixels`` is expected to take at each level: what the level took,
        or (never seen) the nearest seen level's scaled by :data:`PRIOR`."""
        seen = [k for k, b in enumerate(self.bpp) if b is not None]
        out = []
        for k, b in enumerate(self.bpp):
            if b is None:
                if not seen:
                    b = 0.0
                else:
                    j = min(seen, key=lambda s: abs(s - k))
                    b = self.bpp[j] * PRIOR[k] / PRIOR[j]
            out.append(b * pixels)
        return out

    def choose(self, moving: bool, pixels: int, now: Optional[float] = None) -> tuple[int, Level]:
        """The level of the next frame: the still is lossless; a moving frame's level is
        :func:`decide`'s, judged at most once per SETTLE_S."""
        if not moving:
            return -1, STILL
        now = time.monotonic() if now is None else now
        if self.target_fps > 0 and now - self.t_level >= SETTLE_S:
            new = decide(Observed(self.level, self.fps(now), self.starved(now), self.link_bps(now),
                                  self.expected_bytes(pixels), self.target_fps))
            if new != self.level:
                self.level, self.t_level = new, now
                self.changes += 1
        return self.level, LEVELS[self.level] if self.target_fps > 0 else LEVELS[0]

    def stats(self, now: Optional[float] = None) -> dict:
        now = time.monotonic() if now is None else now
        bps = self.link_bps(now)
        lv = LEVELS[self.level]
        return {"level": self.level, "reduce": lv.reduce, "quality": lv.quality,
                "link_mbit_s": round(bps / 1e6, 2) if bps else None, "starved": round(self.starved(now), 2),
                "level_changes": self.changes}


def _reduce(rgba: np.ndarray, k: int) -> np.ndarray:
    """The picture with each side divided by ``k`` (a box filter: every pixel counted)."""
    if k <= 1:
        return rgba
    from PIL import Image

    h, w = rgba.shape[:2]
    img = Image.fromarray(np.ascontiguousarray(rgba[: h - h % k, : w - w % k]), "RGBA")
    return np.asarray(img.reduce(k))


def encode_level(raw, width: int, height: int, level: Level, default_quality: int = 80) -> Encoded:
    """``raw`` (width*height*4 RGBA bytes) encoded at ``level``: PNG for the still, else JPEG
    of the picture reduced by ``level.reduce`` at ``level.quality``."""
    rgba = np.frombuffer(raw, np.uint8)
    if rgba.size != width * height * 4:
        raise ValueError(f"frame has {rgba.size} bytes, expected {width}x{height}x4 = {width * height * 4}")
    rgba = rgba.reshape(height, width, 4)
    t0 = time.perf_counter()
    if level.lossless:
        data, mime = encode_png(rgba), "image/png"
    else:
        data, mime = encode_jpeg(_reduce(rgba, level.reduce), level.quality or default_quality), "image/jpeg"
    return Encoded(data, mime, (time.perf_counter() - t0) * 1e3)

