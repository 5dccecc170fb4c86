"""Helpers for tests that run whole pipelines: leak checks and small configs."""
from __future__ import annotations

import os
import time

import psutil

from pointflow import testing
from pointflow.testing import free_port as free_tcp_port  # noqa: F401  (tests import it here)

SHM = "/dev/shm"


def shm_names() -> set[str]:
    try:
        return set(os.listdir(SHM))
    except FileNotFoundError:
        return set()


def assert_segments_gone(stats: dict) -> None:
    """The pipeline's own shared-memory segments are unlinked (checked by name, so
    other tests running at the same time cannot disturb the check)."""
    segs = stats["shm_segments"]
    assert len(segs) == 3, segs
    left = [s for s in segs if os.path.exists(os.path.join(SHM, s))]
    assert not left, f"leaked shared-memory segments: {left}"


def small_config(**over) -> dict:
    """A fast pipeline: small synthetic scans, small ring, small frames, cpu tier."""
    cfg = {
        "source": {"transport": "synthetic", "options": {"scan_hz": 10, "points_per_scan": 20000}},
        "ring": {"max_points": 100_000},
        "cadence": {"target_hz": 30},
        "render": {"backend": "cpu", "size": [160, 120], "output": {"every_n_frames": 5}},
        "supervisor": {"max_restarts": 0},
    }
    for key, value in over.items():
        section, _, leaf = key.partition("__")
        if leaf:
            cfg.setdefault(section, {})[leaf] = value
        else:
            cfg[section] = value
    return cfg


def assert_gone(pids, timeout=60.0) -> None:
    """Every pid has exited (or is a zombie about to be reaped by nobody we know). The
    guarantee is that no process is left, not how fast they go: a stage stopping on a
    loaded machine (draining, closing sockets) can take seconds."""
    end = time.monotonic() + timeout
    alive = list(pids)
    while alive and time.monotonic() < end:
        alive = [p for p in alive if _alive(p)]
        if alive:
            time.sleep(0.1)
    assert not alive, f"stage processes still running: {alive}"


def _alive(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def wait_for(pred, timeout=30.0, interval=0.1):
    return testing.wait_for(pred, timeout, interval)
