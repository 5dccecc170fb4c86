"""The docs check for Python: every ```python block of README.md and docs/api.md runs, as
written, in a fresh interpreter, and must exit 0 (issue 28: runnable examples).

Each block runs in its own temporary folder (outputs stay out of the clone; the repository's
``configs/`` is linked there, so ``Pipeline.from_yaml("configs/demo.yaml")`` works), with no display
(``pointflow.show`` writes its PNG instead of opening a window). A block may be exempted with
``<!-- docs-check: skip <reason> -->`` as in :mod:`test_docs`. Other docs' Python blocks are
fragments (a plugin class, a reference algorithm) and are not run."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from .test_docs import ROOT, parse

RUN = [ROOT / "README.md", ROOT / "docs" / "api.md"]
BLOCKS = [b for p in RUN for b in parse(p) if b.lang in ("python", "py")]


def test_there_are_python_examples():
    assert any(b.file == "docs/api.md" for b in BLOCKS) and any(b.file == "README.md" for b in BLOCKS)


@pytest.mark.parametrize("block", BLOCKS, ids=[b.id for b in BLOCKS])
def test_python_block_runs(block, tmp_path):
    if block.skip is not None:
        assert block.skip, f"{block.id}: a docs-check skip marker needs a reason"
        pytest.skip(f"docs-check: skip {block.id}: {block.skip}")
    os.symlink(ROOT / "configs", tmp_path / "configs")
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    env["TMPDIR"] = str(tmp_path)
    try:
        p = subprocess.run([sys.executable, "-c", block.text], cwd=tmp_path, env=env, capture_output=True,
                           text=True, timeout=240, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        pytest.fail(f"{block.id}: timed out after 240 s")
    assert p.returncode == 0, f"{block.id} exited {p.returncode}:\n{p.stdout[-2000:]}\n{p.stderr[-4000:]}"
    assert "Traceback" not in p.stderr, f"{block.id}: a traceback reached the user:\n{p.stderr[-4000:]}"
