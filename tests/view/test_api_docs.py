"""The Python examples of docs/api.md's "Steer the view" and "Steer the replay" run as
written (each in a fresh interpreter, from a scratch folder that sees the repository's
configs/), so the docs cannot drift from the API."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SECTIONS = ("## Steer the view", "## Steer the replay")


def _blocks() -> list[tuple[str, str]]:
    text = (ROOT / "docs" / "api.md").read_text()
    out = []
    for head in SECTIONS:
        start = text.index(head)
        nxt = text.find("\n## ", start + len(head))
        body = text[start: nxt if nxt >= 0 else len(text)]
        for m in re.finditer(r"^```python\n(.*?)^```", body, re.S | re.M):
            line = text[: start + m.start()].count("\n") + 1
            out.append((f"docs/api.md:{line}", m.group(1)))
    return out


BLOCKS = _blocks()


def test_the_sections_have_examples():
    assert len(BLOCKS) >= 2


@pytest.mark.parametrize("code", [b[1] for b in BLOCKS], ids=[b[0] for b in BLOCKS])
def test_python_example_runs(code, tmp_path):
    os.symlink(ROOT / "configs", tmp_path / "configs")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, env=env,
                       timeout=240, stdin=subprocess.DEVNULL)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-4000:]
    assert "Traceback" not in r.stderr
