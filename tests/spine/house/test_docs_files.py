"""docs/architecture.md names real files: every repository path it quotes exists, and its
table of processes names each stage kind with the file that declares it (issue 27.5)."""
from __future__ import annotations

import re

from pointflow.stage.kinds import stage_kinds

from .test_docs import ROOT

DOC = ROOT / "docs" / "architecture.md"
PATH = re.compile(r"`((?:pointflow|tests|bench|configs|docs|examples|scripts)/[\w./-]*)`")


def test_every_path_it_names_exists():
    named = set(PATH.findall(DOC.read_text(encoding="utf-8")))
    assert len(named) > 20, named  # the check sees the package map
    missing = sorted(p for p in named if not (ROOT / p).exists())
    assert not missing, f"docs/architecture.md names files that do not exist: {missing}"


def test_the_process_table_names_every_kind_and_its_entry_file():
    text = DOC.read_text(encoding="utf-8")
    table = text[text.index("## Processes"):text.index("## What flows")]
    rows = [ln for ln in table.splitlines() if ln.startswith("| ")]
    for kind in stage_kinds().values():
        entry = kind.main.partition(":")[0].replace(".", "/") + ".py"
        if not entry.startswith("pointflow/"):
            continue  # registered by another test module
        row = next((r for r in rows if f"(`{kind.name}`" in r), None)
        assert row is not None, f"no row for the stage kind {kind.name!r} in the process table"
        assert f"`{entry}`" in row, f"the row of {kind.name!r} does not name its entry file {entry}: {row}"
