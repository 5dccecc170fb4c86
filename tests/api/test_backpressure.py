"""Backpressure, explicit and counted: ``block`` waits while ingest is behind and loses
nothing; ``drop_oldest`` never waits and drops the oldest queued clouds (issue 28, item 1).
Ingest is made to fall behind by stopping it (SIGSTOP), not by timing."""
from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest

from pointflow import Pipeline

from .helpers import api_config

BIG = 100_000  # 2 MB a cloud: more than the socket buffers between us and a stopped ingest


def _pipeline(**api_options):
    cfg = api_config(sources=[{"transport": "api", "name": "api", "options": api_options}],
                     ring={"max_points": 4_000_000},
                     # a SIGSTOPped ingest must not be judged hung during the test
                     supervisor={"standby": False, "hung_after_ms": 120_000, "stall_after_ms": 240_000})
    return Pipeline.from_dict(cfg, out_dir="")


def _cloud(i):
    pos = np.zeros((BIG, 3), np.float32)
    pos[:, 0] = i
    return pos, np.full(BIG, i, np.float32)


def _settle(p, total):
    end = time.monotonic() + 120
    while time.monotonic() < end and p.stats()["accounting"]["ingest_written"] < total:
        time.sleep(0.05)


def test_drop_oldest_never_waits_and_counts_what_it_dropped():
    p = _pipeline(backpressure="drop_oldest", queue_clouds=2)
    p.start()
    ingest = p.stats()["stages"]["ingest"]["pid"]
    os.kill(ingest, signal.SIGSTOP)
    try:
        for i in range(30):
            pos, inten = _cloud(i)
            p.send(pos, intensity=inten)  # returns at once, whatever ingest does
        mid = p.stats()["stages"]["api"]
    finally:
        os.kill(ingest, signal.SIGCONT)
    assert mid["drops"].get("drop_oldest", 0) >= 10 * BIG  # most of the 30 could not wait
    assert mid["queued_points"] <= 3 * BIG
    _settle(p, 30 * BIG - mid["drops"]["drop_oldest"])
    snap = p.supervisor.ring.snapshot()
    stats = p.stop()
    api = stats["stages"]["api"]
    assert api["points_in"] == 30 * BIG == api["points_out"] + api["drops"]["drop_oldest"]
    acc = stats["accounting"]
    assert acc["sources_balanced"] and acc["lost_before_ingest"] == 0
    assert acc["ingest_written"] == api["points_out"]
    # the newest clouds are kept whole, the dropped ones are gone whole and counted exactly
    ids, counts = np.unique(snap.channels["intensity"].astype(int), return_counts=True)
    assert (counts == BIG).all() and ids[-1] == 29 and 28 in ids
    assert (30 - len(ids)) * BIG == api["drops"]["drop_oldest"]


def test_block_waits_while_ingest_is_stopped_and_loses_nothing():
    p = _pipeline(backpressure="block")
    p.start()
    ingest = p.stats()["stages"]["ingest"]["pid"]
    os.kill(ingest, signal.SIGSTOP)
    done = threading.Event()

    def sender():
        for i in range(80):
            pos, inten = _cloud(i)
            p.send(pos, intensity=inten)
        done.set()

    t = threading.Thread(target=sender)
    try:
        t.start()
        assert not done.wait(2.0)  # 80 x 2 MB cannot all be handed to a stopped ingest
    finally:
        os.kill(ingest, signal.SIGCONT)
    t.join(120)
    assert done.is_set()
    _settle(p, 80 * BIG)
    stats = p.stop()
    api = stats["stages"]["api"]
    assert api["points_in"] == api["points_out"] == 80 * BIG and api["drops"] == {}
    assert api["send_blocked_ms"] > 0
    assert stats["accounting"]["ingest_written"] == 80 * BIG and stats["accounting"]["lost_before_ingest"] == 0


@pytest.mark.parametrize("mode", ["block", "drop_oldest"])
def test_arrays_may_be_reused_as_soon_as_send_returns(mode):
    """One buffer, overwritten after every send while ingest is stopped (so every message is
    still in flight): the ring holds each cloud as it was when sent."""
    p = _pipeline(backpressure=mode, queue_clouds=20)
    p.start()
    ingest = p.stats()["stages"]["ingest"]["pid"]
    pos, inten = _cloud(0)
    os.kill(ingest, signal.SIGSTOP)
    try:
        for i in range(10):
            pos[:, 0] = i
            inten[:] = i
            p.send(pos, intensity=inten)
    finally:
        os.kill(ingest, signal.SIGCONT)
    _settle(p, 10 * BIG)
    snap = p.supervisor.ring.snapshot()
    stats = p.stop()
    assert stats["stages"]["api"]["points_out"] == 10 * BIG
    ids, counts = np.unique(snap.channels["intensity"].astype(int), return_counts=True)
    assert ids.tolist() == list(range(10)) and (counts == BIG).all()
    np.testing.assert_array_equal(snap.positions[:, 0], snap.channels["intensity"].astype(np.float64))
