"""Ticker: absolute deadlines (no drift), late ticks never push the schedule, skips counted."""
import pytest

from pointflow.cadence.ticker import Ticker

from .fakeclock import FakeClock


def test_deadlines_are_absolute_no_drift_with_oversleep():
    clk = FakeClock(oversleep=0.003)  # every sleep wakes 3 ms late
    t = Ticker(1 / 60, clock=clk, sleep=clk.sleep, spin_s=0)
    ticks = [t.wait() for _ in range(600)]
    # served deadlines are exactly anchor + k/60: lateness never accumulates
    assert [tk.index for tk in ticks] == list(range(1, 601))
    for tk in ticks:
        assert tk.deadline == pytest.approx(100.0 + tk.index / 60, abs=1e-9)
        assert tk.late_s == pytest.approx(0.003, abs=1e-9)
    assert t.missed == 0
    # 600 ticks at 60 Hz take 10 s (+ one oversleep), not 600 * (1/60 + 3 ms)
    assert clk.t - 100.0 == pytest.approx(10.003, abs=1e-6)


def test_late_tick_does_not_push_next_back():
    clk = FakeClock()
    t = Ticker(0.010, clock=clk, sleep=clk.sleep, spin_s=0)
    assert t.wait().index == 1
    clk.advance(0.007)              # work took 7 ms of the 10 ms period
    tk = t.wait()
    assert tk.index == 2 and tk.late_s == pytest.approx(0.0)
    assert clk.t == pytest.approx(100.020)
    clk.advance(0.012)              # overran: wakes 2 ms after deadline 3 ...
    tk = t.wait()
    assert tk.index == 3 and tk.late_s == pytest.approx(0.002) and tk.missed == 0
    tk = t.wait()                   # ... but deadline 4 stays at 100.040
    assert tk.index == 4 and tk.deadline == pytest.approx(100.040) and clk.t == pytest.approx(100.040)


def test_unservable_ticks_are_skipped_and_counted_not_queued():
    clk = FakeClock()
    t = Ticker(0.010, clock=clk, sleep=clk.sleep, spin_s=0)
    t.wait()
    clk.advance(0.0355)             # stalled through deadlines 2, 3 and 4 (due at 20, 30, 40 ms)
    tk = t.poll()
    assert tk.index == 4 and tk.missed == 2 and tk.late_s == pytest.approx(0.0055)
    assert t.missed == 2
    assert t.poll() is None         # nothing queued: the next tick is deadline 5
    assert t.next_deadline == pytest.approx(100.050)
    assert t.ticks == 2


def test_wait_uses_idle_and_returns_none_at_max_wait():
    clk = FakeClock()
    idles = []

    def idle(s):
        idles.append(s)
        clk.advance(s)

    t = Ticker(0.100, clock=clk, sleep=clk.sleep, spin_s=0.002)
    assert t.wait(idle=idle, max_wait_s=0.030) is None
    assert clk.t == pytest.approx(100.030)
    tk = t.wait(idle=idle)
    assert tk.index == 1 and clk.t == pytest.approx(100.100)
    # the coarse part goes to idle, the last spin_s to the precise sleep
    assert idles[-1] == pytest.approx(0.070 - 0.002)
    assert clk.sleeps[-1] == pytest.approx(0.002)


def test_set_interval_rebases_on_last_deadline():
    clk = FakeClock()
    t = Ticker(0.010, clock=clk, sleep=clk.sleep, spin_s=0)
    t.wait(); t.wait()              # deadlines 100.010, 100.020
    t.set_interval(0.050)
    tk = t.wait()
    assert tk.deadline == pytest.approx(100.070)
    assert t.wait().deadline == pytest.approx(100.120)


def test_bad_interval_rejected():
    with pytest.raises(ValueError, match="interval"):
        Ticker(0)
    t = Ticker(0.1)
    with pytest.raises(ValueError, match="interval"):
        t.set_interval(-1)
