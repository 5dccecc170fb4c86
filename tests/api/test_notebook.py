"""Pipeline.send and pointflow.show from a Jupyter kernel (a real ipykernel process, driven
by jupyter_client as a notebook front end drives it) (issue 28, items 1 and 5)."""
from __future__ import annotations

import importlib.util
import json
import os

import pytest

from .helpers import REPO, api_config

jupyter_client = pytest.importorskip("jupyter_client", reason="jupyter_client comes with the test extra: pip install 'pointflow[test]'")
pytest.importorskip("ipykernel", reason="ipykernel comes with the test extra: pip install 'pointflow[test]'")


def _run(kc, code: str, timeout: float = 180) -> str:
    """Execute ``code`` in the kernel; its stdout, or the kernel's error as a failure."""
    msg_id = kc.execute(code)
    out = []
    while True:
        msg = kc.get_iopub_msg(timeout=timeout)
        if msg["parent_header"].get("msg_id") != msg_id:
            continue
        kind, content = msg["msg_type"], msg["content"]
        if kind == "stream":
            out.append(content["text"])
        elif kind == "execute_result":  # a cell's value, as the notebook shows it
            out.append("RESULT " + content["data"].get("text/plain", "") + "\n")
        elif kind == "display_data":
            out.extend(f"DISPLAY {mime}\n" for mime in content["data"])
        elif kind == "error":
            pytest.fail("kernel error: " + "\n".join(content["traceback"])[-3000:])
        elif kind == "status" and content["execution_state"] == "idle":
            return "".join(out)


def test_send_and_show_from_a_kernel(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    km = jupyter_client.KernelManager(kernel_name="python3")
    km.start_kernel(cwd=str(tmp_path), env=env)
    kc = km.client()
    kc.start_channels()
    try:
        kc.wait_for_ready(timeout=120)
        cfg = api_config()
        out = _run(kc, f"""
import json, numpy as np, pointflow
from pointflow import Pipeline
from pointflow.show import in_notebook
print("IN_NOTEBOOK", in_notebook())
p = Pipeline.from_dict(json.loads({json.dumps(json.dumps(cfg))}), out_dir="")
p.start()
for i in range(10):
    p.send(np.full((1000, 3), i, np.float32), intensity=np.full(1000, i, np.float32))
p.wait(60, until=lambda: p.stats()["accounting"]["ring_written"] == 10_000)
stats = p.stop()
print("WRITTEN", stats["accounting"]["ring_written"], stats["stages"]["api"]["points_out"])
""")
        assert "IN_NOTEBOOK True" in out
        assert "WRITTEN 10000 10000" in out
        # a cell ending in p.stop() shows one line, not the whole stats dict
        out = _run(kc, f"""
p = Pipeline.from_dict(json.loads({json.dumps(json.dumps(cfg))}), out_dir="")
p.start()
p.send(np.zeros((500, 3), np.float32), intensity=np.zeros(500, np.float32))
p.wait(60, until=lambda: p.stats()["accounting"]["ring_written"] == 500)
p.stop()
""")
        result = [line for line in out.splitlines() if line.startswith("RESULT ")]
        assert len(result) == 1 and result[0].startswith("RESULT Stopped(frames=") and "ring_written=500" in result[0], out
        out = _run(kc, 'print("STATS", p.stop()["accounting"]["ring_written"], type(p.stop()).__mro__[1].__name__)')
        assert "STATS 500 dict" in out, out
        # with the notebook extra, show displays the live widget (pointflow.notebook)
        if importlib.util.find_spec("anywidget") is not None:
            out = _run(kc, """
r = pointflow.show(np.random.default_rng(0).normal(size=(2000, 3)), size=(96, 64))
print("RETURNED", r)
""")
            assert "DISPLAY application/vnd.jupyter.widget-view+json" in out and "RETURNED None" in out, out
        # the PNG view, asked for by name
        out = _run(kc, """
path = pointflow.show(np.random.default_rng(0).normal(size=(2000, 3)), path="nb.png", size=(96, 64), view="png")
print("PNG", path)
""")
        assert f"PNG {tmp_path / 'nb.png'}" in out and (tmp_path / "nb.png").stat().st_size > 0
    finally:
        kc.stop_channels()
        km.shutdown_kernel(now=True)
