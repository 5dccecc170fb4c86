"""Issue 19.7: a test run stopped with SIGTERM removes its network namespaces and the
``pointflow run`` processes in them, as docs/remote.md promises for every way a run ends."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import psutil

from . import netns

INNER = textwrap.dedent('''
    import time
    from pathlib import Path

    from tests.remote.conftest import net, _sweep_namespaces  # noqa: F401 - the real fixtures


    def test_holds_a_namespace_and_a_pipeline(net, tmp_path):
        ns = net.host("a")
        cfg = tmp_path / "c.yaml"
        cfg.write_text("source: {transport: synthetic, options: {points_per_scan: 2000}}\\n"
                       "render: {backend: cpu, size: [64, 48]}\\n")
        p = net.pointflow(ns, "run", str(cfg), "--duration", "600", "-q", "--out", str(tmp_path / "out"), log="run.log")
        Path(MARK).write_text(f"{net.tag} {p.pid}")
        time.sleep(600)
''')


def test_sigterm_of_the_test_run_leaves_no_namespace_or_process(tmp_path):
    netns.require_netns()
    mark = tmp_path / "mark"
    (tmp_path / "test_inner.py").write_text(f"MARK = {str(mark)!r}\n" + INNER)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(netns.REPO), *sys.path]))
    proc = subprocess.Popen([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-s",
                             str(tmp_path / "test_inner.py")], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        end = time.monotonic() + 120
        while not mark.exists() and time.monotonic() < end and proc.poll() is None:
            time.sleep(0.1)
        assert mark.exists(), proc.communicate(timeout=30)[0][-3000:] if proc.poll() is not None else "inner test never started"
        tag, pid = mark.read_text().split()
        run_pid = int(pid)
        time.sleep(1.0)  # the pipeline is up (its stages started)
        family = [run_pid] + [c.pid for c in psutil.Process(run_pid).children(recursive=True)]
        assert any(ns.startswith(f"{netns.PREFIX}{tag}") for ns in netns.list_namespaces())
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=90)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    left_ns = [ns for ns in netns.list_namespaces() if ns.startswith(f"{netns.PREFIX}{tag}")]
    assert not left_ns, f"namespaces left: {left_ns}\n{out[-2000:]}"
    end = time.monotonic() + 10
    alive = family
    while alive and time.monotonic() < end:
        alive = [p for p in family if psutil.pid_exists(p) and psutil.Process(p).status() != psutil.STATUS_ZOMBIE]
        time.sleep(0.1)
    assert not alive, f"processes left: {alive}\n{out[-2000:]}"
    assert proc.returncode != 0  # the run was stopped, not passed
