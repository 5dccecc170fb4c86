"""The one bench engine (pyzmq's ``perf/perf.py`` is the model: one engine, drivers on top).

Every script in ``bench/`` is a driver that imports only this package and ``pointflow``.
Scripts run as ``python bench/<script>.py``: Python puts the script's folder first on
``sys.path``, so ``import _harness`` finds this package without anyone setting ``sys.path``;
``pointflow`` is the installed one (``pip install -e .``) or the tree named by ``PYTHONPATH``
(the machine description records which one was measured).

What it holds: set-up (``XDG_RUNTIME_DIR``, paths), ONE machine description
(:func:`machine` / :func:`machine_done`), timing loops (:func:`median_ms`, :func:`per_call`),
interleaved A/B (:func:`interleave`, :class:`Worker`, :func:`run_json`, :func:`revision_tree`),
result writing (:func:`write_result`) and the matplotlib guard (:func:`pyplot`).
"""
from __future__ import annotations

import contextlib
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

#: the checkout this bench/ folder belongs to
ROOT = Path(__file__).resolve().parents[2]
BENCH = ROOT / "bench"
RESULTS = BENCH / "results"
#: the real recordings: $POINTFLOW_DATA, else ../shared/data beside the checkout (or beside
#: the worktrees' parent)
DATA = Path(os.environ["POINTFLOW_DATA"]) if os.environ.get("POINTFLOW_DATA") else next(
    (p for p in (ROOT.parent / "shared" / "data", ROOT.parents[1] / "shared" / "data") if p.is_dir()),
    ROOT.parent / "shared" / "data")


# ----------------------------------------------------------------------------- set-up
def setup() -> str:
    """A private ``XDG_RUNTIME_DIR`` (wgpu/Mesa want one; it holds the ipc:// sockets): the
    caller's, else ``/tmp/pointflow-xdg-<uid>`` as the Makefile and the tests use. Runs on
    import, so a driver has it before it imports ``pointflow``."""
    d = os.environ.get("XDG_RUNTIME_DIR") or os.path.join(tempfile.gettempdir(), f"pointflow-xdg-{os.getuid()}")
    os.makedirs(d, mode=0o700, exist_ok=True)
    os.environ["XDG_RUNTIME_DIR"] = d
    return d


setup()


def command() -> str:
    """How this run was started, relative to the checkout (written next to its figures)."""
    script = Path(sys.argv[0]).resolve()
    try:
        script = script.relative_to(ROOT)
    except ValueError:
        pass
    return " ".join([str(script), *sys.argv[1:]])


# ----------------------------------------------------------------------------- machine
def uptime() -> str:
    """``uptime``'s line (load averages over 1, 5, 15 min), or the load averages alone."""
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "load average: " + ", ".join(f"{x:.2f}" for x in os.getloadavg())


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def git_revision(root: Path | str = ROOT) -> str | None:
    """The commit of ``root`` (``+dirty`` when its tracked files differ), or None outside git."""
    try:
        rev = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True,
                             text=True, timeout=10)
        if rev.returncode:
            return None
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10).stdout.strip()
        return rev.stdout.strip() + ("+dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return None


def _pointflow_path() -> str | None:
    import importlib.util

    spec = importlib.util.find_spec("pointflow")
    return str(Path(spec.origin).parent) if spec and spec.origin else None


def machine(adapter: str | None = None, **extra: Any) -> dict[str, Any]:
    """The one machine description written next to every figure: CPU, cores, load before
    (``machine_done`` adds the load after), the GPU adapter when known, the code measured
    (git revision of this checkout, the ``pointflow`` package used). The machine is shared
    with other work: the load says how busy it was."""
    pf = _pointflow_path()
    d: dict[str, Any] = {
        "host": platform.node(), "cpu": _cpu_model(), "cores": os.cpu_count(),
        "platform": platform.platform(), "python": platform.python_version(),
        "git": git_revision(), "pointflow": pf, "adapter": adapter,
        "started_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "loadavg_before": [round(x, 2) for x in os.getloadavg()], "uptime_before": uptime(),
        "shared": "the machine is shared with other work; the load averages say how busy it was",
    }
    if "pointflow" in sys.modules and pf and not Path(pf).resolve().is_relative_to(ROOT):  # this process measures it
        print(f"note: measuring pointflow from {pf}, not this checkout ({ROOT}); set PYTHONPATH={ROOT} "
              "to measure this one", file=sys.stderr)
    d.update(extra)
    return d


def machine_done(d: dict[str, Any]) -> dict[str, Any]:
    """Add the load after the run to a :func:`machine` description (returns it)."""
    d["loadavg_after"] = [round(x, 2) for x in os.getloadavg()]
    d["uptime_after"] = uptime()
    d["ended_at"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    return d


def machine_line(d: dict[str, Any]) -> str:
    """A :func:`machine` description in one line, for a chart's corner."""
    load = f"load {d['loadavg_before'][0]:.1f}"
    if "loadavg_after" in d:
        load += f" -> {d['loadavg_after'][0]:.1f}"
    return f"{d['host'][:20]} ({d['cores']} CPUs), {load}" + (f", {d['adapter']}" if d.get("adapter") else "")


# ----------------------------------------------------------------------------- timing
def median_ms(fn: Callable[[], Any], reps: int, warm: int = 1) -> tuple[float, list[float]]:
    """(median, every sample) of ``fn``'s wall time in ms over ``reps`` calls after ``warm``."""
    for _ in range(warm):
        fn()
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        ts.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(ts), ts


def batch_time(fn: Callable[[], Any], min_s: float) -> float:
    """Seconds per call over one batch of at least ``min_s`` (and two calls)."""
    reps, t0 = 0, time.perf_counter()
    while True:
        fn()
        reps += 1
        d = time.perf_counter() - t0
        if d >= min_s and reps >= 2:
            return d / reps


def per_call(fn: Callable[[], Any], batches: int = 7, min_s: float = 0.05, warm: int = 50) -> list[float]:
    """Seconds per call of a fast ``fn``: ``batches`` batches (:func:`batch_time`), after
    ``warm`` calls; one figure per batch."""
    for _ in range(warm):
        fn()
    return [batch_time(fn, min_s) for _ in range(batches)]


def cpu_seconds(ps) -> float:
    """CPU time of a process (a psutil.Process), all its threads (ZeroMQ's I/O thread
    included): from the scheduler's ns counters (/proc/PID/task/*/schedstat) where there are
    any, else psutil's (10 ms ticks: too coarse for a 0.1 s measurement)."""
    try:
        tot = 0
        base = f"/proc/{ps.pid}/task"
        for tid in os.listdir(base):
            with open(f"{base}/{tid}/schedstat") as f:
                tot += int(f.read().split()[0])
        return tot / 1e9
    except (OSError, ValueError, IndexError):
        c = ps.cpu_times()
        return c.user + c.system


def spread(values: Sequence[float]) -> dict[str, Any]:
    """median, min, max and n of some samples."""
    v = list(values)
    return {"median": statistics.median(v), "min": min(v), "max": max(v), "n": len(v)}


# ----------------------------------------------------------------------------- interleaved A/B
def order(keys: Sequence[str], i: int) -> list[str]:
    """Round ``i``'s order: as given on even rounds, reversed on odd ones (ABBA...), so a
    drift in the machine's load hits every side alike."""
    return list(keys) if i % 2 == 0 else list(reversed(keys))


def interleave(runners: dict[str, Callable[[], Any]], rounds: int,
               on_result: Callable[[int, str, Any], None] | None = None) -> dict[str, list[Any]]:
    """Run each of ``runners`` once per round, alternating the order (:func:`order`); every
    result per side, in round order. ``on_result(round, key, result)`` prints progress."""
    out: dict[str, list[Any]] = {k: [] for k in runners}
    for i in range(rounds):
        for k in order(list(runners), i):
            r = runners[k]()
            out[k].append(r)
            if on_result is not None:
                on_result(i, k, r)
    return out


def checkout_env(root: Path | str, **extra: str) -> dict[str, str]:
    """The environment that makes a child process import ``root``'s ``pointflow`` (before
    any installed one) and find the shared data from wherever ``root`` is."""
    return dict(os.environ, PYTHONPATH=str(Path(root).resolve()), POINTFLOW_DATA=str(DATA), **extra)


def _child(args: Sequence[str], root: Path | str | None) -> dict[str, Any]:
    """argv, env and cwd of a child that imports ``root``'s pointflow: run from ``root`` (so
    ``python -c``/``-m``, whose first path entry is the working folder, find it too) with a
    script named by its absolute path."""
    argv = [str(Path(a).resolve()) if i == 0 and Path(str(a)).is_file() else str(a) for i, a in enumerate(args)]
    if root is None:
        return {"args": [sys.executable, *argv]}
    return {"args": [sys.executable, *argv], "env": checkout_env(root), "cwd": str(root)}


def run_json(args: Sequence[str], root: Path | str | None = None, **kw: Any) -> Any:
    """Run ``python ARGS`` (against ``root``'s pointflow when given) and parse its stdout as
    JSON: one measurement in a fresh process."""
    p = subprocess.run(**_child(args, root), capture_output=True, text=True, **kw)
    if p.returncode:
        raise RuntimeError(f"{' '.join(map(str, args))} failed ({p.returncode}): {p.stderr[-2000:]}")
    return json.loads(p.stdout)


class Worker:
    """A long-lived measuring process that answers one JSON line per command line (so two
    checkouts can be timed batch by batch, each set up once)."""

    def __init__(self, args: Sequence[str], root: Path | str | None = None):
        self.p = subprocess.Popen(**_child(args, root), stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)

    def ask(self, line: str) -> Any:
        assert self.p.stdin and self.p.stdout
        self.p.stdin.write(line + "\n")
        self.p.stdin.flush()
        out = self.p.stdout.readline()
        if not out:
            raise RuntimeError(f"worker died on {line!r}")
        return json.loads(out)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.ask("quit")
        try:
            self.p.wait(timeout=60)
        except subprocess.TimeoutExpired:
            self.p.kill()
            self.p.wait(5)


def resolve_revision(rev: str, root: Path | str = ROOT) -> str:
    """The full commit a revision name means in ``root``'s repository."""
    p = subprocess.run(["git", "-C", str(root), "rev-parse", "--verify", f"{rev}^{{commit}}"], capture_output=True,
                       text=True)
    if p.returncode:
        raise SystemExit(f"not a revision of {root}: {rev!r} ({p.stderr.strip()})")
    return p.stdout.strip()


@contextlib.contextmanager
def revision_tree(rev: str, root: Path | str = ROOT) -> Iterator[Path]:
    """A private copy of revision ``rev``'s tracked files (``git archive``: a detached work
    tree that leaves the repository's branches, index and worktree list alone), removed after."""
    sha = resolve_revision(rev, root)
    d = Path(tempfile.mkdtemp(prefix=f"pf-rev-{sha[:8]}-"))
    try:
        arch = subprocess.Popen(["git", "-C", str(root), "archive", sha], stdout=subprocess.PIPE)
        subprocess.run(["tar", "-x", "-C", str(d)], stdin=arch.stdout, check=True)
        if arch.wait():
            raise SystemExit(f"git archive {sha} failed")
        yield d
    finally:
        shutil.rmtree(d, ignore_errors=True)


@contextlib.contextmanager
def checkout_or_revision(rev: str, root: Path | str = ROOT) -> Iterator[tuple[Path, str]]:
    """(folder, full commit) of a revision for an A/B run: ``.`` is this checkout as it is
    (uncommitted changes included), anything else a private copy (:func:`revision_tree`)."""
    if rev == ".":
        yield Path(root), git_revision(root) or "."
        return
    with revision_tree(rev, root) as d:
        yield d, resolve_revision(rev, root)


def ab_arguments(ap: Any, sizes: Sequence[int], rounds: int, out: str) -> None:
    """The options every ``--child`` A/B driver takes (:func:`ab_child_rounds`)."""
    ap.add_argument("--base", help="the revision to compare against (required)")
    ap.add_argument("--head", default=".", help="a revision, or . for this checkout as it is (default)")
    ap.add_argument("--sizes", type=int, nargs="*", default=list(sizes))
    ap.add_argument("--rounds", type=int, default=rounds, help="rounds per size (each: one process per side)")
    ap.add_argument("--out", default=str(RESULTS / out))
    ap.add_argument("--child", type=int, default=0, help="(internal: one side's measurement at this size)")


def ab_child_rounds(me: str, base: str, head: str, sizes: Sequence[int], rounds: int,
                    args: Callable[[int], list[str]], warm: Sequence[str] | None = None,
                    digits: int = 2) -> tuple[str, str, list[dict[str, Any]]]:
    """An A/B of a driver's ``--child`` between revisions ``base`` and ``head``: per size,
    ``rounds`` rounds of one fresh process per side (``me`` + ``args(n)``, run against that
    side's checkout, printing a JSON dict of figures in ms), the sides alternating (ABBA);
    ``warm`` is run once per side first (e.g. to compile). Returns (base commit, head commit,
    one row per size: the figures' medians over rounds, head/base and every sample)."""
    rows = []
    with checkout_or_revision(base) as (bdir, bsha), checkout_or_revision(head) as (hdir, hsha):
        sides = {"base": bdir, "head": hdir}
        if warm:
            for d in sides.values():
                run_json([me, *warm], d)
        for n in sizes:
            got: dict[str, list[dict[str, float]]] = {"base": [], "head": []}
            for i in range(rounds):
                for side in (("base", "head") if i % 2 == 0 else ("head", "base")):
                    got[side].append(run_json([me, *args(n)], sides[side]))
            row: dict[str, Any] = {"points": n, "rounds": rounds, "load_after": [round(x, 2) for x in os.getloadavg()],
                                   "figures": {}}
            for k in got["base"][0]:
                b = float(statistics.median([r[k] for r in got["base"]]))
                h = float(statistics.median([r[k] for r in got["head"]]))
                row["figures"][k] = {"base_ms": round(b, digits), "head_ms": round(h, digits),
                                     "head_over_base": round(h / b, 3),
                                     "base_samples": [round(r[k], digits) for r in got["base"]],
                                     "head_samples": [round(r[k], digits) for r in got["head"]]}
                print(f"{n:>9,} {k:28s} base {b:8.2f} ms  head {h:8.2f} ms  x{h / b:.2f}", flush=True)
            rows.append(row)
    return bsha, hsha, rows


# ----------------------------------------------------------------------------- results
def write_result(path: Path | str, res: dict[str, Any], indent: int = 2) -> Path:
    """Write a result JSON (folders made), say where."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(res, indent=indent, default=str))
    print(f"wrote {p}", flush=True)
    return p


def pyplot():
    """matplotlib's pyplot on the Agg backend, or None (with a note) where the ``plot`` extra
    is not installed: charts are optional, figures are not."""
    try:
        import matplotlib
    except ImportError:
        print("matplotlib not installed (pip install 'pointflow[plot]'): no chart", file=sys.stderr)
        return None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
