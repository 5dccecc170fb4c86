"""A stage's error reaches the user once (issue 31.5, generalised): a stage that crashes past its
restart limit used to print its exception itself, then the supervisor ("reported: ..."), then the
supervisor again with the exit, the CLI again and the summary line. Now the supervisor's line
with the exit code and the last error is the only one; the summary line names the stage."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from ..helpers import assert_segments_gone, small_config

REPO = Path(__file__).resolve().parents[3]

PLUGIN = '''
from pointflow.ingest.transports.base import Transport


class Crashes(Transport):
    name = "crashes"

    def open(self):
        raise RuntimeError("the sensor said no-such-thing-31")

    def chunks(self):
        yield None
'''


@pytest.mark.timeout(180)
@pytest.mark.parametrize("restarts", [0, 1])
def test_a_crashing_stage_is_printed_once(tmp_path, restarts):
    (tmp_path / "crash31_plugin.py").write_text(PLUGIN)
    cfg = small_config(source={"transport": "crash31_plugin:Crashes"}, supervisor={"max_restarts": restarts},
                       render={"backend": "cpu", "size": [64, 48], "output": {"dir": str(tmp_path / "out")}})
    path = tmp_path / "c.yaml"
    path.write_text(json.dumps(cfg))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), str(tmp_path)]))
    r = subprocess.run([sys.executable, "-m", "pointflow.cli", "run", str(path), "--duration", "60", "-q"],
                       capture_output=True, text=True, timeout=150, env=env, cwd=tmp_path)
    out = r.stdout + r.stderr
    assert r.returncode == 2, (r.returncode, out[-3000:])
    assert "Traceback" not in out, out[-3000:]
    lines = [ln for ln in out.splitlines() if "no-such-thing-31" in ln]
    # one line per death: each restart is news, the last one ends the run
    assert len(lines) == restarts + 1, "\n".join(lines)
    assert "RuntimeError: the sensor said no-such-thing-31" in lines[-1] and "restart limit" in lines[-1], lines
    assert any("FAILED (stage source" in ln for ln in r.stdout.splitlines()), r.stdout
    stats = json.loads((tmp_path / "out" / "stats.json").read_text())
    assert "no-such-thing-31" in stats["stages"]["source"]["last_error"]  # the whole traceback is kept
    assert_segments_gone(stats)
