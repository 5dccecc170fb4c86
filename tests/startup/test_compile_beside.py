"""The render stage never waits for numba's compiler (issue 36): on an empty cache, or one
a killed compiler left half filled, it draws with the float64 reference raster at once,
compiles the compiled raster's loops in a process of its own, and switches between two
frames; a cache that cannot be written is said once and the reference keeps drawing.

Real processes throughout: a pipeline with an ``api`` source and ``render: {backend: cpu,
raster: compute}`` (the reference is what draws meanwhile), numba's cache in a private
``NUMBA_CACHE_DIR`` the stages inherit. Every wait is on a condition (a stats key, a file),
never a sleep, with limits far above a compile on a loaded 2-core machine (~70 s at load 12).
"""
from __future__ import annotations

import glob
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from pointflow import Pipeline
from pointflow.render.base import FrameInput
from pointflow.render.camera import Camera
from pointflow.render.cpu import CpuRenderer

pytest.importorskip("numba")

REPO = Path(__file__).resolve().parents[2]
#: a compile from nothing, under load, with margin
COMPILE_LIMIT_S = 900
#: the compiled raster against the reference: test_cpu_compute's bound (<= 0.1% of pixels)
BOUND = 0.001
CAMERA = {"mode": "fixed", "position": [0.0, -30.0, 12.0], "target": [0.0, 0.0, 0.0], "near": 0.5, "far": 200.0}


def _config() -> dict:
    return {
        "sources": [{"transport": "api", "name": "api"}],
        "ring": {"max_points": 50_000},
        "cadence": {"target_hz": 10},
        "render": {"backend": "cpu", "raster": "compute", "size": [160, 90], "color_by": "intensity",
                   "color_range": [0.0, 1.0], "point_size": 3, "camera": CAMERA, "output": {"dir": None}},
        "tracing": {"enabled": False},
        "supervisor": {"standby": False},
    }


def _scene() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(36)
    pos = (rng.random((20_000, 3)) * [20.0, 20.0, 4.0] - [10.0, 10.0, 2.0]).astype(np.float32)
    return pos, rng.random(20_000).astype(np.float32)


def _reference(cfg, pos, inten) -> np.ndarray:
    """The float64 reference drawing the scene in this process (what the stage should show)."""
    n = pos.shape[0]
    r = CpuRenderer(cfg.render, n, ["intensity"])
    f = FrameInput(positions=pos, importance=np.ones(n, np.float32), t_ingest_ms=np.zeros(n),
                   channels={"intensity": inten}, head=0, size=n, capacity=n, origin=np.zeros(3), now_ms=0.0,
                   channel_ranges={"intensity": (0.0, 1.0)})
    c = cfg.render.camera
    r.render(f, Camera(eye=c.position, target=c.target, up=c.up, fov_deg=c.fov_deg, near=c.near, far=c.far))
    return r.read_image()


def _render(p) -> dict:
    return p.stats()["stages"]["render"]


def _wait(p, cond, limit_s: float, what: str) -> dict:
    end = time.monotonic() + limit_s
    while time.monotonic() < end:
        r = _render(p)
        if cond(r):
            return r
        time.sleep(0.1)
    raise AssertionError(f"{what} not within {limit_s:.0f} s; render stats: "
                         f"{ {k: v for k, v in _render(p).items() if k.startswith(('raster', 'frames', 'tier'))} }")


def _saved(p, path: Path) -> np.ndarray:
    return np.asarray(Image.open(p.save_frame(str(path))).convert("RGBA"))


def _diff(a: np.ndarray, b: np.ndarray) -> float:
    return float((a != b).any(axis=-1).mean())


def _draw_then_switch(tmp: Path, tag: str) -> dict:
    """One pipeline: the first frame comes from the reference while the compiler works, then
    the compiled raster takes over and draws the same picture (within BOUND)."""
    pos, inten = _scene()
    p = Pipeline.from_dict(_config(), out_dir="")
    want = _reference(p.cfg, pos, inten)
    p.start()
    try:
        p.send(pos, intensity=inten)
        # a frame of the whole cloud (one drawn while ingest was still writing it is a part)
        r = _wait(p, lambda r: r.get("frames", 0) >= 1 and r.get("drawn_count", 0) >= len(pos), 120,
                  "a first frame of the whole cloud")
        assert r["raster"] in ("compiling", "compiled"), r["raster"]
        meanwhile = _saved(p, tmp / f"{tag}-meanwhile.png")
        if _render(p)["raster"] == "compiling":  # still the reference's picture
            assert _diff(meanwhile, want) <= BOUND
        r = _wait(p, lambda r: r.get("raster") == "compiled", COMPILE_LIMIT_S, "the switch to the compiled raster")
        assert r["raster_switched_at_frame"] >= 1, "a frame was drawn before the compiled raster was ready"
        assert r["tier_info"].get("raster") == "compute"
        at = r["raster_switched_at_frame"]
        _wait(p, lambda r: r["frames"] > at, 120, "a frame of the compiled raster")
        got = _saved(p, tmp / f"{tag}-compiled.png")
        assert (got != got[0, 0]).any(axis=-1).mean() > 0.05, "the scene must cover the image"
        d = _diff(got, want)
        assert d <= BOUND, f"compiled raster differs from the reference in {d:.3%} of pixels"
    finally:
        stats = p.stop()
    return stats


def _compiler_done(cache: Path) -> None:
    """Wait until no compiler holds a lock in ``cache`` (a detached compiler outlives a run)."""
    from pointflow import jitcache

    end = time.monotonic() + COMPILE_LIMIT_S
    while time.monotonic() < end:
        if not any(jitcache.compiling(os.path.dirname(f)) for f in glob.glob(str(cache / "*" / jitcache.LOCK_NAME))):
            return
        time.sleep(0.2)


_CHECK = """
import glob, os, pickle, sys
from pointflow.render import cpu_kernels
bad = []
for nbi in glob.glob(os.path.join(sys.argv[1], "*", "*.nbi")):
    with open(nbi, "rb") as f:
        pickle.load(f)                      # numba's version
        stamp, entries = pickle.loads(f.read())
    for key, name in entries.items():
        try:
            with open(os.path.join(os.path.dirname(nbi), name), "rb") as f:
                pickle.loads(f.read())
        except Exception as exc:
            bad.append(f"{name}: {type(exc).__name__}")
print(cpu_kernels.cache_state(), len(glob.glob(os.path.join(sys.argv[1], "*", "*.nbi"))), bad)
"""


@pytest.mark.timeout(COMPILE_LIMIT_S + 300)
def test_empty_cache_draws_at_once_and_switches_to_the_compiled_raster(tmp_path, monkeypatch):
    """Empty NUMBA_CACHE_DIR: a frame before the compiler is done (counted in
    ``raster_switched_at_frame``, so no race with a fast compile), then the compiled raster's
    picture equals the reference's within BOUND. Under load only the waits grow."""
    cache = tmp_path / "numba"
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(cache))
    try:
        _draw_then_switch(tmp_path, "empty")
    finally:
        _compiler_done(cache)


@pytest.mark.timeout(2 * COMPILE_LIMIT_S + 300)
def test_a_compiler_killed_midway_leaves_a_cache_the_next_run_completes(tmp_path, monkeypatch):
    """The compiler is SIGKILLed once it has written part of the cache; every index entry
    left names a complete data file, and the next run draws at once, compiles the rest and
    switches (same picture as the reference). Under load the kill lands later in the
    compile; the guarantees do not depend on where."""
    cache = tmp_path / "numba"
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(cache))
    pos, inten = _scene()
    p = Pipeline.from_dict(_config(), out_dir="")
    p.start()
    try:
        p.send(pos, intensity=inten)
        r = _wait(p, lambda r: r.get("frames", 0) >= 1 and "raster_compiler_pid" in r, 120,
                  "a first frame and a compiler")
        pid = r["raster_compiler_pid"]
        end = time.monotonic() + COMPILE_LIMIT_S
        while not glob.glob(str(cache / "*" / "*.nbi")) and time.monotonic() < end:
            time.sleep(0.05)
        os.kill(pid, signal.SIGKILL)
    finally:
        p.stop()
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", _CHECK, str(cache)], capture_output=True, text=True, env=env,
                         timeout=300)
    state, n_index, bad = out.stdout.strip().split(" ", 2)
    assert int(n_index) >= 1 and bad == "[]", out.stdout + out.stderr
    try:
        _draw_then_switch(tmp_path, "after-kill")
    finally:
        _compiler_done(cache)
    assert not glob.glob(str(cache / "*" / "*.tmp.*")), "the next compiler sweeps half-written files"


def test_a_cache_numba_cannot_write_is_said_once_and_the_reference_draws(tmp_path, monkeypatch, capfd):
    """No writable cache location (numba's only locator pointed below a file): one warning
    naming NUMBA_CACHE_DIR, no compiler, and the reference draws. Load changes nothing."""
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(blocker / "numba"))
    monkeypatch.setenv("NUMBA_CACHE_LOCATOR_CLASSES", "UserProvidedCacheLocator")
    pos, inten = _scene()
    p = Pipeline.from_dict(_config(), out_dir="")
    want = _reference(p.cfg, pos, inten)
    p.start()
    try:
        p.send(pos, intensity=inten)
        # a frame of the whole cloud (one drawn while ingest was still writing it is a part)
        r = _wait(p, lambda r: r.get("frames", 0) >= 1 and r.get("drawn_count", 0) >= len(pos), 120,
                  "a first frame of the whole cloud")
        assert r["raster"] == "reference" and "raster_compiler_pid" not in r and r["raster_meanwhile"] is None
        assert _diff(_saved(p, tmp_path / "ref.png"), want) <= BOUND
        at = r["frames"]
        _wait(p, lambda r: r["frames"] > at or r.get("frames_skipped_unchanged", 0) > 3, 60, "the stage going on")
    finally:
        p.stop()
    err = capfd.readouterr().err
    assert err.count("numba cannot cache the compiled raster") == 1, err[-3000:]
    assert "NUMBA_CACHE_DIR" in err


_FRAMES = """
import sys, time
import numpy as np
from pointflow.frames import compiled, kernels
first = compiled.load()
where = compiled._pending
print("first", first is None, where is not None, flush=True)  # a compiler was started for it
src = np.arange(30, dtype=np.float32).reshape(10, 3)
R, t = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]), np.array([10.0, 20.0, 3.0])
before = kernels.rigid(src, R, t)      # numpy meanwhile
end = time.monotonic() + float(sys.argv[1])
k = None
while k is None and time.monotonic() < end:
    time.sleep(0.2)
    k = compiled.load()
out = np.empty(30, np.float32)
k.rigid(src.reshape(-1), R, t, out)
print("later", k is not None, np.allclose(out.reshape(10, 3), before.astype(np.float32)), flush=True)
"""


@pytest.mark.timeout(COMPILE_LIMIT_S + 120)
def test_the_frames_loops_never_hold_up_the_first_points(tmp_path):
    """On an empty cache the frames transform's first load() returns at once with no compiled
    loops (numpy places the points) while a compiler fills the cache; a later load() returns
    them, and they place points as numpy did. Load only lengthens the wait for the later one."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"),
               PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("POINTFLOW_NO_NUMBA", None)
    try:
        out = subprocess.run([sys.executable, "-c", _FRAMES, str(COMPILE_LIMIT_S)], capture_output=True, text=True,
                             env=env, timeout=COMPILE_LIMIT_S + 60)
        assert "first True True" in out.stdout and "later True True" in out.stdout, out.stdout + out.stderr[-2000:]
    finally:
        _compiler_done(tmp_path / "numba")
