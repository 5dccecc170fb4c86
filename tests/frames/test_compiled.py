"""The compiled rigid transform (pointflow/frames/compiled.py) gives the numpy path's answer,
loads in a fresh process with an unusable cache directory, and is optional (numpy fallback)."""
import os
import subprocess
import sys

import numpy as np
import pytest

from pointflow.frames import compiled
from pointflow.frames.kernels import RigidTransform, Scratch, rigid
from pointflow.frames.rotation import from_rpy, to_matrix
from pointflow.ring import PointRing


def _case(seed):
    rng = np.random.default_rng(seed)
    R = to_matrix(from_rpy(*rng.uniform(-3, 3, 3)))
    t = rng.uniform(-50, 50, 3) + (np.array([4.5e5, 5.1e6, 30.0]) if seed % 2 else 0.0)
    origin = np.round(t + rng.uniform(-20, 20, 3))
    return R, t, origin, rng


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_compiled_equals_numpy_into_float32(dtype):
    assert compiled.load() is not None, "numba is a core dependency: the kernel must load here"
    for seed in range(12):
        R, t, origin, rng = _case(seed)
        src = rng.uniform(-150, 150, (7001, 3)).astype(dtype)
        xf = RigidTransform(R, t, Scratch())
        got = np.full(3 * src.shape[0], np.nan, np.float32)
        xf.apply(src, origin, got)
        ref = np.empty((src.shape[0], 3), np.float32)
        rigid(src, R, t - origin, Scratch(), out=ref)
        exact = (src.astype(np.float64) @ R.T + (t - origin)).astype(np.float32).reshape(-1)
        # float64 throughout, rounded once: within an ulp of numpy's (BLAS sums in its own order)
        ulp = np.abs(got.view(np.int32).astype(np.int64) - ref.reshape(-1).view(np.int32))
        assert ulp.max() <= 1
        assert np.abs(got.view(np.int32).astype(np.int64) - exact.view(np.int32)).max() <= 1


def test_compiled_takes_read_only_inputs():
    R, t, origin, rng = _case(3)
    src = np.frombuffer(rng.uniform(-9, 9, 300).astype(np.float32).tobytes(), np.float32).reshape(100, 3)
    R = R.copy()
    R.setflags(write=False)
    out = np.empty(300, np.float32)
    RigidTransform(R, t).apply(src, origin, out)
    ref = np.empty((100, 3), np.float32)
    rigid(src, R, t - origin, out=ref)
    assert np.abs(out - ref.reshape(-1)).max() <= 2 * np.spacing(np.abs(ref).max())


def test_cache_failure_compiles_without_cache(monkeypatch):
    real = compiled._compile
    calls = []

    def compile_(cache):
        calls.append(cache)
        if cache:
            raise RuntimeError("cannot cache function: no locator available")
        return real(cache)

    monkeypatch.setattr(compiled, "_compile", compile_)
    monkeypatch.setattr(compiled, "_tried", False)
    monkeypatch.setattr(compiled, "_kernel", None)
    k = compiled.load()
    assert calls == [True, False] and k is not None
    src = np.ones((4, 3), np.float32)
    out = np.empty(12, np.float32)
    k.rigid(src.reshape(-1), np.eye(3), np.array([1.0, 2.0, 3.0]), out)
    assert np.array_equal(out.reshape(4, 3), np.array([[2.0, 3.0, 4.0]] * 4, np.float32))


_CHILD = """
import numpy as np
from pointflow.frames import compiled
from pointflow.frames.kernels import RigidTransform
from pointflow.ring import PointRing
k = compiled.load()
xf = RigidTransform(np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]), np.array([10.0, 20.0, 3.0]))
with PointRing(100) as r:
    src = np.arange(30, dtype=np.float32).reshape(10, 3)
    r.push(src, value_range=xf.bounds(0.0, 29.0), transform=xf)  # the first push picks the origin
    r.push(src + 1, value_range=xf.bounds(1.0, 30.0), transform=xf)  # this one goes through apply()
    s = r.snapshot()
    print(k is not None, np.array_equal(s.positions, np.concatenate([xf.world(src), xf.world(src + 1)])))
"""


@pytest.mark.parametrize("env", [{"NUMBA_CACHE_DIR": "/dev/null/not-a-dir"}, {"POINTFLOW_NO_NUMBA": "1"}])
def test_fresh_process_places_points_with_or_without_the_kernel(env):
    """An unusable NUMBA_CACHE_DIR (not even creatable) still gives the kernel; without numba
    (forced) the numpy path gives the same points."""
    out = subprocess.run([sys.executable, "-c", _CHILD], env={**os.environ, **env}, capture_output=True, text=True,
                         timeout=240)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["False" if "POINTFLOW_NO_NUMBA" in env else "True", "True"]


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_compiled_deskew_loops_equal_the_numpy_path_bit_for_bit(dtype, monkeypatch):
    """apply_table and apply_nodes: the compiled loops do numpy's sums in numpy's order."""
    from pointflow.frames import deskew as dk

    rng = np.random.default_rng(7)
    n, u, k = 20_000, 700, 40
    pos = rng.uniform(-120, 120, (n, 3)).astype(dtype)
    R = np.stack([to_matrix(from_rpy(*rng.uniform(-3, 3, 3))) for _ in range(max(u, k))])
    t = rng.uniform(-50, 50, (max(u, k), 3))
    idx = rng.integers(0, u, n).astype(np.intp)
    nodes = np.linspace(0.0, 1e8, k)
    off = rng.uniform(-1e6, 1.01e8, n)  # a few before the first node and after the last: clipped
    got = (dk.apply_table(pos, idx, R[:u], t[:u], Scratch()), dk.apply_nodes(pos, off, nodes, R[:k], t[:k], Scratch()))
    monkeypatch.setattr(compiled, "load", lambda: None)
    ref = (dk.apply_table(pos, idx, R[:u], t[:u], Scratch()), dk.apply_nodes(pos, off, nodes, R[:k], t[:k], Scratch()))
    assert np.array_equal(got[0], ref[0])
    assert np.array_equal(got[1], ref[1])


_PREPARE = """
import sys
from pointflow.config import load_config
from pointflow.ingest import process
from pointflow.frames import compiled
process.prepare(load_config({"source": {"transport": "synthetic"}}), None, None)
print("numba" in sys.modules)  # frames off: nothing loaded, no numba import
process.prepare(load_config({"source": {"transport": "synthetic"}, "frames": {"fixed": "odom"}}), None, None)
print("numba" in sys.modules, compiled.load() is not None)
"""


def test_numba_is_imported_only_for_frames_and_prepare_loads_it():
    """Importing ingest costs nothing extra; a standby's prepare loads the loops when
    frames.fixed is set (so an activated ingest does not pay it)."""
    out = subprocess.run([sys.executable, "-c", _PREPARE], capture_output=True, text=True, timeout=240)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["False", "True", "True"]


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_compiled_placed_positions_in_float64_equal_numpy(dtype, monkeypatch):
    """kernels.rigid into float64 (recording, thinning, small clouds of a dynamic chain):
    the compiled pass against numpy's product, within an ulp of float64."""
    R, t, _, rng = _case(5)
    src = rng.uniform(-150, 150, (40_000, 3)).astype(dtype)
    got = rigid(src, R, t, Scratch())
    monkeypatch.setattr(compiled, "load", lambda: None)
    ref = rigid(src, R, t, Scratch())
    assert np.abs(got - ref).max() <= 2 * np.spacing(np.abs(ref).max())
    exact = src.astype(np.float64) @ R.T + t
    assert np.abs(got - exact).max() <= 2 * np.spacing(np.abs(exact).max())
