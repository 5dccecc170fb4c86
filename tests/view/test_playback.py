"""Steering a replay through real processes: pause holds, seek lands on the computed message,
step moves by one, rate 2 halves the replay time, loop repeats, bad arguments are refused
and the replay goes on; the CLI's --start/--rate/--loop.

The recording is 20 scan files at 10 scans/s (message i at i / 10 s); file i holds 100 + i
points, so the points that arrive tell which message went."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml

from pointflow import Pipeline
from pointflow.ingest.playback import PlaybackError

N = 20
RATE = 10.0


def _scans(path) -> str:
    d = os.path.join(path, "scans")
    os.makedirs(d, exist_ok=True)
    for i in range(N):
        n = 100 + i
        np.savez(os.path.join(d, f"s{i:03d}.npz"), x=np.full(n, float(i)), y=np.arange(n, dtype=float),
                 z=np.zeros(n))
    return d


def _config(scans: str, **playback) -> dict:
    return {"source": {"transport": "file", "name": "rec", "options": {"path": scans, "rate": RATE}},
            "ring": {"max_points": 10000}, "cadence": {"target_hz": 20}, "playback": playback,
            "render": {"backend": "cpu", "size": [64, 48], "output": {"every_n_frames": 100000}}}


def _points_in(pipe) -> int:
    return pipe.stats()["stages"]["rec"]["points_in"]


def _settle(pipe, expect: int) -> int:
    """Wait until the source's count reaches ``expect`` (and report the count)."""
    pipe.wait(30, until=lambda: _points_in(pipe) >= expect)
    pipe.wait(0.5)  # nothing more arrives
    return _points_in(pipe)


def _size(i: int) -> int:
    return 100 + i


def test_pause_step_seek_rate_loop(tmp_path):
    scans = _scans(str(tmp_path))
    with Pipeline.from_dict(_config(scans, paused=True, hold=True), out_dir=str(tmp_path)) as pipe:
        st = pipe.playback()["rec"]
        assert st["paused"] and st["duration_s"] == pytest.approx(N / RATE) and st["messages"] == N
        pipe.wait(1.5)
        assert _points_in(pipe) == 0, "a paused replay sent points"

        # step: exactly one message, the first
        pipe.playback(step=1)
        assert _settle(pipe, _size(0)) == _size(0)
        assert pipe.playback()["rec"]["index"] == 0

        # seek to 1.05 s lands on message 11 (the first at or after it: 1.1 s); paused, it goes
        # once (a view shows where the seek landed) and the replay stays paused
        st = pipe.playback(seek_s=1.05)["rec"]
        assert st["seeks"] == 1
        got = _settle(pipe, _size(0) + _size(11))
        assert got == _size(0) + _size(11)
        st = pipe.playback()["rec"]
        assert st["index"] == 11 and st["position_s"] == pytest.approx(1.1) and st["paused"]
        pipe.playback(step=1)  # a step sends the next
        got = _settle(pipe, got + _size(12))
        assert got == _size(0) + _size(11) + _size(12)

        # seek by fraction: 0.5 of 2 s = 1.0 s = message 10 (shown); two steps send 11 and 12
        pipe.playback(seek_fraction=0.5)
        got = _settle(pipe, got + _size(10))
        pipe.playback(step=2)
        got = _settle(pipe, got + _size(11) + _size(12))
        assert got == _size(0) + 2 * (_size(11) + _size(12)) + _size(10)
        assert pipe.playback()["rec"]["index"] == 12

        # bad arguments: each refused, naming it; the replay state is unchanged and goes on
        for kwargs, key, words in [({"seek_s": 2.5}, "seek_s", "past the end"),
                                   ({"seek_fraction": 1.5}, "seek_fraction", "<= 1"),
                                   ({"rate": float("nan")}, "rate", "finite"),
                                   ({"rate": 0.0}, "rate", ">= 0.001"),
                                   ({"step": -1}, "step", ">= 0"),
                                   ({"source": "nope"}, "source", "rec")]:
            with pytest.raises(PlaybackError) as exc:
                pipe.playback(**kwargs)
            assert exc.value.key == key and words in str(exc.value), str(exc.value)
        st = pipe.playback()["rec"]
        assert st["index"] == 12 and st["paused"] and st["rate"] == 1.0
        assert _points_in(pipe) == got

        # rate: replay messages 0..19 at rate 1 and at rate 2; the second takes about half as long
        def replay(rate: float) -> float:
            before = _points_in(pipe)
            pipe.playback(paused=True, seek_s=0.0, rate=rate)  # paused: message 0 goes once
            before = _settle(pipe, before + _size(0))
            t0 = time.monotonic()
            pipe.playback(paused=False)
            total = sum(_size(i) for i in range(1, N))
            pipe.wait(60, until=lambda: _points_in(pipe) >= before + total)
            assert _points_in(pipe) == before + total
            return time.monotonic() - t0

        t1 = replay(1.0)
        t2 = replay(2.0)
        # 1.9 s of recording between the first and the last message: 1.9 s vs 0.95 s, plus the
        # time the counts take to show up (heartbeats), the same in both
        assert 0.3 < t2 / t1 < 0.8, (t1, t2)
        assert pipe.stats()["stages"]["rec"]["restarts"] == 0


def test_seek_returns_once_landed(tmp_path):
    """``playback(seek_*)`` and ``playback(step=n)`` return the state after they landed: the
    sought message has gone out (paused too: it goes once), the steps have gone out, a seek past
    the last message is at the end. No poll after it: the returned state itself shows it."""
    scans = _scans(str(tmp_path))
    with Pipeline.from_dict(_config(scans, paused=True, hold=True), out_dir=str(tmp_path)) as pipe:
        st = pipe.playback(step=1)["rec"]
        assert st["index"] == 0 and st["steps_pending"] == 0
        st = pipe.playback(seek_s=1.05)["rec"]  # paused: message 11 (1.1 s) goes once
        assert not st["seek_pending"] and st["seeks_landed"] == st["seeks"] == 1
        assert st["index"] == 11 and st["position_s"] == pytest.approx(1.1) and st["paused"]
        st = pipe.playback(seek_fraction=0.25)["rec"]  # 0.5 s: message 5
        assert st["index"] == 5 and st["position_s"] == pytest.approx(0.5) and st["seeks_landed"] == 2
        st = pipe.playback(step=1)["rec"]
        assert st["index"] == 6 and st["paused"]
        assert _settle(pipe, _size(0) + _size(11) + _size(5) + _size(6)) == _size(0) + _size(11) + _size(5) + _size(6)

        st = pipe.playback(seek_s=1.95)["rec"]  # past the last message (1.9 s): at the end (hold)
        assert st["seeks_landed"] == 3 and st["next_s"] is None and st["index"] == 6
        pipe.wait(10, until=lambda: pipe.playback()["rec"]["at_end"])
        assert pipe.playback()["rec"]["at_end"]

        pipe.playback(rate=0.01, paused=False, seek_s=0.0)  # playing, slowly (10 s a message)
        st = pipe.playback(seek_s=1.2)["rec"]  # playing: message 12 has gone out
        assert not st["seek_pending"] and st["seeks_landed"] == st["seeks"] == 5
        assert st["index"] == 12 and st["position_s"] == pytest.approx(1.2) and not st["paused"]


def test_loop_repeats_and_pause_holds(tmp_path):
    scans = _scans(str(tmp_path))
    total = sum(_size(i) for i in range(N))
    with Pipeline.from_dict(_config(scans, rate=4.0, loop=True), out_dir=str(tmp_path)) as pipe:
        pipe.wait(60, until=lambda: pipe.stats()["stages"]["rec"].get("transport_loops", 0) >= 2)
        assert pipe.stats()["stages"]["rec"]["transport_loops"] >= 2
        assert _points_in(pipe) >= 2 * total  # two whole passes (the loop count goes up as the third starts)
        pipe.playback(paused=True)
        pipe.wait(0.5)
        held = _points_in(pipe)
        pipe.wait(1.5)
        assert _points_in(pipe) == held, "points kept coming while paused"
        pipe.playback(loop=False, paused=False)
        pipe.wait(30, until=lambda: not pipe.stats()["stages"]["rec"]["alive"])
        assert _points_in(pipe) % total == 0 and _points_in(pipe) > held  # the paused pass ran on to its end


def test_cli_start_rate_loop(tmp_path):
    scans = _scans(str(tmp_path))
    cfg = _config(scans)
    del cfg["playback"]
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(cfg))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [os.getcwd(), os.environ.get("PYTHONPATH")])))
    out = tmp_path / "out"
    # until the replay has ended (its "finished" line), then Ctrl-C: a fixed --duration would
    # also count start-up, which a loaded machine can stretch past the replay's end
    r = subprocess.Popen([sys.executable, "-m", "pointflow.cli", "run", str(path), "--start", "50%", "--rate", "4",
                          "--duration", "240", "--out", str(out), "-q"], stdin=subprocess.DEVNULL,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    err = []
    for line in r.stderr:
        err.append(line)
        if "rec finished (its input ended)" in line:
            r.send_signal(signal.SIGINT)
    r.communicate(timeout=120)
    assert r.returncode == 0 and any("rec finished" in ln for ln in err), "".join(err)[-3000:]
    stats = json.loads((out / "stats.json").read_text())
    assert stats["stages"]["rec"]["points_in"] == sum(_size(i) for i in range(N // 2, N))
    assert stats["config"]["playback"]["rate"] == 4.0
    bad = subprocess.run([sys.executable, "-m", "pointflow.cli", "run", str(path), "--rate", "-1", "--duration", "1"],
                         capture_output=True, text=True, env=env, timeout=60)
    assert bad.returncode != 0 and "--rate" in bad.stderr and "Traceback" not in bad.stderr, bad.stderr
