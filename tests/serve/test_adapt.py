"""The link policy (render/view/adapt.py): a pure function of what was observed, and the
per-client observations that feed it. Times are given, never slept."""
from __future__ import annotations

import io

import numpy as np
import pytest

from pointflow.render.view.adapt import LEVELS, STILL, Link, Observed, decide, encode_level

PX = 1280 * 720
#: a plausible ladder of frame sizes at 1280x720 (bytes), best level first
SIZES = [180_000, 120_000, 60_000, 43_000, 30_000, 14_000]


def obs(level=0, fps=30.0, starved=0.0, link_bps=None, target=20.0):
    return Observed(level, fps, starved, link_bps, SIZES, target)


def test_a_fast_link_keeps_full_quality():
    assert decide(obs(fps=30, starved=0.1, link_bps=1e9)) == 0


def test_slow_and_starved_goes_down_to_what_fits():
    # 10 Mbit/s at 20 frames/s with 80 % headroom: 50 kB a frame -> the first level under it
    assert decide(obs(fps=7, starved=0.95, link_bps=10e6)) == 3
    # 2 Mbit/s: nothing fits: the smallest
    assert decide(obs(fps=2, starved=0.95, link_bps=2e6)) == len(LEVELS) - 1


def test_at_least_one_step_down_when_starved_and_slow():
    assert decide(obs(level=0, fps=10, starved=0.9, link_bps=None)) == 1  # not measured yet: one step


def test_starved_under_target_goes_down_though_the_rate_would_carry_it():
    # two frames a round trip: on a long link a smaller frame is a shorter trip, more frames/s
    assert decide(obs(level=0, fps=10, starved=0.9, link_bps=100e6)) == 1
    assert decide(obs(level=3, fps=12, starved=0.9, link_bps=10e6)) == 4


def test_a_slow_render_is_not_the_links_fault():
    # under target but the credit was mostly unused: lowering the quality would not help
    assert decide(obs(level=0, fps=8, starved=0.1, link_bps=10e6)) == 0
    assert decide(obs(level=3, fps=8, starved=0.1, link_bps=10e6)) == 3


def test_up_one_step_only_with_room_to_spare():
    # at target, link 40 Mbit/s: budget 200 kB, level 2 (60 kB) fits well under 0.75 of it
    assert decide(obs(level=3, fps=25, starved=0.2, link_bps=40e6)) == 2
    # 10 Mbit/s: budget 50 kB, level 2's 60 kB does not fit: stay
    assert decide(obs(level=3, fps=25, starved=0.2, link_bps=10e6)) == 3
    # 15 Mbit/s: budget 75 kB, 60 kB fits but not with the hysteresis' room (56 kB): stay
    assert decide(obs(level=3, fps=25, starved=0.2, link_bps=15e6)) == 3


def test_unknown_fps_or_adaptation_off_keeps_the_level():
    assert decide(obs(level=2, fps=None, starved=1.0, link_bps=1e6)) == 2
    assert decide(obs(level=2, fps=1, starved=1.0, link_bps=1e6, target=0)) == 2


def _feed(link: Link, t0: float, n: int, dt: float, nbytes: int, rtt: float, back_to_back: bool) -> float:
    """Frames of ``nbytes`` acknowledged every ``dt`` s, each written ``rtt`` before its ack
    (back to back: written before the previous ack), credit all out when starved."""
    t = t0
    for _ in range(n):
        start = t - (dt + 0.001 if back_to_back else rtt)
        link.sent(nbytes, True, start)
        link.flight(back_to_back, start)  # both frames out (starved) only when back to back
        link.acked(t)
        link.encoded(link.level, nbytes, PX)
        t += dt
    return t


def test_link_measures_the_rate_of_frames_sent_back_to_back():
    link = Link(target_fps=20)
    t = _feed(link, 100.0, 20, 0.1, 125_000, 0.04, back_to_back=True)  # 125 kB / 0.1 s = 10 Mbit/s
    assert link.link_bps(t) == pytest.approx(10e6, rel=0.02)
    assert link.fps(t) == pytest.approx(10, rel=0.15)
    assert link.starved(t) > 0.9
    level, how = link.choose(True, PX, now=t)
    assert level > 0 and (how.reduce > 1 or how.quality < 80)
    assert link.changes == 1


def test_link_rests_lossless_and_stays_when_render_is_slow():
    link = Link(target_fps=20)
    t = _feed(link, 100.0, 20, 0.1, 125_000, 0.04, back_to_back=False)
    assert link.starved(t) < 0.5
    assert link.choose(True, PX, now=t)[0] == 0  # 10 frames/s, but render's: the quality stays
    assert link.choose(False, PX, now=t) == (-1, STILL)


def test_expected_bytes_scale_the_seen_level_by_the_prior():
    link = Link()
    link.encoded(0, 180_000, PX)
    e = link.expected_bytes(PX)
    assert e[0] == pytest.approx(180_000)
    assert e[2] < e[1] < e[0] and e[-1] < e[2]


def test_encode_level_reduces_and_the_still_is_lossless():
    from PIL import Image

    rng = np.random.default_rng(0)
    rgba = rng.integers(0, 255, (72, 128, 4), dtype=np.uint8)
    rgba[..., 3] = 255
    still = encode_level(rgba.tobytes(), 128, 72, STILL)
    assert still.mime == "image/png"
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(still.data)).convert("RGB")), rgba[..., :3])
    half = encode_level(rgba.tobytes(), 128, 72, LEVELS[2])
    assert half.mime == "image/jpeg" and Image.open(io.BytesIO(half.data)).size == (64, 36)
    quarter = encode_level(rgba.tobytes(), 128, 72, LEVELS[-1])
    assert Image.open(io.BytesIO(quarter.data)).size == (32, 18)
    with pytest.raises(ValueError, match="expected 128x72x4"):
        encode_level(b"\0" * 10, 128, 72, STILL)
