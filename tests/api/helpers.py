"""Configs and a script runner for the api tests (real processes: the scripts run as a
user's would, without a main guard, in a fresh interpreter)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def api_config(**over) -> dict:
    """One api source, a small ring keeping intensity and rgb, the cpu tier, no PNGs."""
    cfg = {
        "sources": [{"transport": "api", "name": "api"}],
        "ring": {"max_points": 200_000, "extra_channels": ["rgb"]},
        "cadence": {"target_hz": 5},
        "render": {"backend": "cpu", "size": [64, 48], "color_by": "intensity", "output": {"dir": None}},
        "tracing": {"enabled": False},
        "supervisor": {"standby": False},
    }
    cfg.update(over)
    return cfg


def run_script(tmp: Path, body: str, timeout: float = 180) -> subprocess.CompletedProcess:
    """Write ``body`` to a .py file (no ``if __name__ == "__main__"`` guard) and run it."""
    path = tmp / "user_script.py"
    path.write_text(textwrap.dedent(body))
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.run([sys.executable, str(path)], cwd=tmp, capture_output=True, text=True, timeout=timeout,
                       env=env, stdin=subprocess.DEVNULL)
    assert p.returncode == 0, f"script failed ({p.returncode}):\n{p.stdout[-3000:]}\n{p.stderr[-5000:]}"
    return p


def known_clouds(k: int, n: int, seed: int = 0):
    """``k`` clouds of ``n`` distinct points on a 1/8 grid (exact in float32 offsets), with an
    intensity that names the cloud and point, and an rgb."""
    import numpy as np

    rng = np.random.default_rng(seed)
    out = []
    for i in range(k):
        idx = np.arange(n) + i * n
        pos = np.stack([idx % 200, (idx // 200) % 200, idx // 40000], axis=1).astype(np.float32) / 8
        inten = (idx + 0.5).astype(np.float32)
        rgb = rng.integers(0, 255, size=(n, 3)).astype(np.uint8)
        out.append((pos, inten, rgb))
    return out


def read_json(path: Path) -> dict:
    return json.loads(path.read_text())


def until(cond, timeout: float, what: str):
    """``cond()``'s first truthy value, polled every 50 ms; a test failure naming ``what``
    after ``timeout`` s (a condition, not a time: the tests hold on a busy machine)."""
    import time

    import pytest

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        got = cond()
        if got:
            return got
        time.sleep(0.05)
    pytest.fail(f"timed out waiting for {what}")
