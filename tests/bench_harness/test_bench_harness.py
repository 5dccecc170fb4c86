"""bench/ is one harness with drivers on top (issue 27): no script sets ``sys.path`` or imports
another script or tests/, and the harness's A/B runner interleaves its sides and writes the
machine description next to what it measured (a tiny real run)."""
from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
BENCH = REPO / "bench"
SCRIPTS = sorted(BENCH.glob("*.py"))
HARNESS = sorted((BENCH / "_harness").glob("*.py"))
#: what a driver may not import: another script, tests/ or one of its packages
FORBIDDEN = ({p.stem for p in SCRIPTS} | {"tests", "bench", "conftest"}
             | {p.name for p in (REPO / "tests").iterdir() if p.is_dir()})


def _imports(tree: ast.AST) -> set[str]:
    out = set()
    for n in ast.walk(tree):
        if isinstance(n, ast.Import):
            out |= {a.name.split(".")[0] for a in n.names}
        elif isinstance(n, ast.ImportFrom) and not n.level:
            out.add((n.module or "").split(".")[0])
        elif isinstance(n, ast.Call) and getattr(n.func, "attr", getattr(n.func, "id", "")) in (
                "import_module", "__import__") and n.args and isinstance(n.args[0], ast.Constant):
            out.add(str(n.args[0].value).split(".")[0])
    return out


def _touches_sys_path(tree: ast.AST) -> list[int]:
    return [n.lineno for n in ast.walk(tree) if isinstance(n, ast.Attribute) and n.attr == "path"
            and isinstance(n.value, ast.Name) and n.value.id == "sys"]


@pytest.mark.parametrize("path", SCRIPTS + HARNESS, ids=lambda p: str(p.relative_to(BENCH)))
def test_script_imports_only_the_harness_and_the_library(path):
    tree = ast.parse(path.read_text(), str(path))
    assert not _touches_sys_path(tree), f"{path.name} uses sys.path at lines {_touches_sys_path(tree)}"
    bad = sorted(_imports(tree) & FORBIDDEN)
    assert not bad, f"{path.name} imports {bad}: a driver imports only _harness and pointflow"


def test_bench_scripts_were_found():
    assert len(SCRIPTS) >= 20 and (BENCH / "_harness" / "__init__.py").is_file()


def test_ab_runner_interleaves_and_writes_the_machine(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))  # as Python does for a script in bench/
    import numpy as np

    import _harness as H

    a, b = np.random.default_rng(0).random((2, 20_000))
    calls: list[str] = []

    def side(k, fn):
        def run():
            calls.append(k)
            return min(H.per_call(fn, batches=2, min_s=0.002, warm=1))
        return run

    machine = H.machine()
    runs = H.interleave({"A": side("A", lambda: np.add(a, b)), "B": side("B", lambda: np.multiply(a, b))}, 4)
    assert calls == ["A", "B", "B", "A", "A", "B", "B", "A"]  # ABBA: load drift hits both sides alike
    assert [len(v) for v in runs.values()] == [4, 4] and all(x > 0 for v in runs.values() for x in v)
    out = H.write_result(tmp_path / "ab.json", {"runs": runs, "machine": H.machine_done(machine),
                                                "command": H.command()})
    m = json.loads(out.read_text())["machine"]
    for key in ("cpu", "cores", "loadavg_before", "loadavg_after", "uptime_before", "uptime_after", "git",
                "pointflow", "adapter"):
        assert key in m, f"machine description lacks {key}: {m}"
    assert m["cores"] == os.cpu_count() and len(m["loadavg_before"]) == 3 and len(m["loadavg_after"]) == 3
    assert Path(m["pointflow"], "__init__.py").is_file()


def test_checkout_env_points_a_child_at_that_checkout(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))
    import _harness as H

    (tmp_path / "pointflow").mkdir()
    (tmp_path / "pointflow" / "__init__.py").write_text("MARK = 'the other checkout'\n")
    got = H.run_json(["-c", "import json, pointflow; print(json.dumps([pointflow.MARK, pointflow.__file__]))"],
                     tmp_path)
    assert got == ["the other checkout", str(tmp_path / "pointflow" / "__init__.py")]


def test_driver_runs_without_sys_path_help(tmp_path):
    """Converted drivers run as ``python bench/<script>.py`` (the harness found beside them) and
    write their result with the machine description (bench_ring.py on its smallest budget)."""
    out = tmp_path / "ring.json"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    p = subprocess.run([sys.executable, str(BENCH / "ab_ring_push.py"), "--help"], capture_output=True, text=True,
                       env=env, timeout=120)
    assert p.returncode == 0 and "checkout A" in p.stdout, p.stderr
    p = subprocess.run([sys.executable, str(BENCH / "bench_ring.py"), "--quick", "--repeats", "1", "--out", str(out)],
                       capture_output=True, text=True, env=env, timeout=240)
    assert p.returncode == 0, p.stderr[-2000:]
    res = json.loads(out.read_text())
    assert res["machine"]["cores"] == os.cpu_count() and "loadavg_after" in res["machine"]
    assert res["command"].startswith("bench/bench_ring.py") and res["ingest"] and res["snapshot"]


def test_machine_ceiling_sizes_its_loops_and_times_both(monkeypatch):
    """The thread bench's same-round baseline (bench_cpu_threads.py): both loops are sized from
    a one-thread timing within their bounds (no timing is compared here: the machine is shared),
    the caller's thread count is left as it was, and each call reports both loops at the current
    thread count, the compute loop having done its work."""
    monkeypatch.syspath_prepend(str(BENCH))
    import numba
    import numpy as np
    from _harness.machine_ceiling import Ceiling

    prev = numba.get_num_threads()
    c = Ceiling(ms=2.0)
    assert numba.get_num_threads() == prev  # sizing leaves the caller's thread count
    assert 256 <= len(c._a) <= 1 << 20 and (1 << 16) <= len(c._x) <= 1 << 25
    for t in sorted({1, numba.config.NUMBA_NUM_THREADS}):
        numba.set_num_threads(t)
        got = c.time(repeat=1)
        assert set(got) == {"compute", "stream"} and all(v > 0 for v in got.values())
        ref = np.array([sum(np.sin(x + j) for j in range(256)) for x in c._a[:4]])
        assert np.allclose(c._out[:4], ref) and np.array_equal(c._y[:8], c._x[:8] * 2.0 + 1.0)
    numba.set_num_threads(prev)
