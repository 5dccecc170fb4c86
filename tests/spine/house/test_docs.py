"""The docs check: what README.md and docs/*.md show a user must be true.

* every fenced ```yaml block is loaded with the config loader: a complete config (it has
  ``source``/``sources``), or a fragment of top-level keys that must validate when merged
  onto ``{source: {transport: synthetic}}``;
* every line of a ```sh / ```bash / ```console block that starts with ``pointflow `` (after
  an optional prompt such as ``$ `` or ``sensor$ ``) is run from the repository root and
  must exit 0: durations shortened to {DURATION} s, ``--out``/``--dir``/``>`` outputs sent to
  a temporary folder, identical commands run once;
* the line ``<!-- docs-check: skip <reason> -->`` directly before a fence exempts that
  block; the reason is required and shows in pytest's skip summary (``-ra``).

One test per block, named ``file:line`` of its fence, so a failure points at the doc.
"""
from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import pytest
import yaml

from pointflow.config import ConfigError, load_config

ROOT = Path(__file__).resolve().parents[3]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
DURATION = "1.5"
FENCE = re.compile(r"^(\s*)(`{3,}|~{3,})\s*([\w+-]*)")
SKIP = re.compile(r"^\s*<!--\s*docs-check:\s*skip\b(.*?)-->\s*$")
COMMAND = re.compile(r"^(?:[\w.@-]*\$\s+)?(pointflow\s.*)$")
SHELL_LANGS = {"sh", "bash", "console", "shell"}


@dataclass
class Block:
    file: str
    line: int          # 1-based line of the opening fence
    lang: str
    text: str
    skip: Optional[str]  # None: checked; otherwise the marker's reason ("" = missing)

    @property
    def id(self) -> str:
        return f"{self.file}:{self.line}"


def parse(path: Path) -> list[Block]:
    lines = path.read_text(encoding="utf-8").splitlines()
    out, i = [], 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        indent, fence, lang = m.group(1), m.group(2), m.group(3).lower()
        start, body = i, []
        i += 1
        while i < len(lines) and not lines[i].strip().startswith(fence):
            body.append(lines[i][len(indent):] if lines[i].startswith(indent) else lines[i].lstrip())
            i += 1
        i += 1
        marker = SKIP.match(lines[start - 1]) if start else None
        out.append(Block(str(path.relative_to(ROOT)), start + 1, lang, "\n".join(body),
                         marker.group(1).strip() if marker else None))
    return out


BLOCKS = [b for p in DOCS for b in parse(p)]
YAML_BLOCKS = [b for b in BLOCKS if b.lang in ("yaml", "yml")]
SHELL_BLOCKS = [b for b in BLOCKS if b.lang in SHELL_LANGS and any(COMMAND.match(l.strip()) for l in b.text.splitlines())]


def _skip(block: Block) -> None:
    if block.skip is not None:
        assert block.skip, f"{block.id}: a docs-check skip marker needs a reason"
        pytest.skip(f"docs-check: skip {block.id}: {block.skip}")


# --------------------------------------------------------------------------- YAML
@pytest.mark.parametrize("block", YAML_BLOCKS, ids=[b.id for b in YAML_BLOCKS])
def test_yaml_block_is_a_valid_config(block: Block):
    _skip(block)
    try:
        data = yaml.safe_load(block.text)
    except yaml.YAMLError as exc:
        pytest.fail(f"{block.id}: not YAML: {' '.join(str(exc).split())}")
    assert isinstance(data, dict), f"{block.id}: a yaml block must be a pointflow config (or mark it skip)"
    if "source" not in data and "sources" not in data:
        data = {"source": {"transport": "synthetic"}, **data}
    try:
        load_config(data, base_dir=str(ROOT))
    except ConfigError as exc:
        pytest.fail(f"{block.id}: the config loader refuses this block: {exc}")


# --------------------------------------------------------------------------- commands
def rewrite(line: str) -> tuple[list[str], Optional[str]]:
    """argv (outputs under ``{tmp}``, durations shortened) and a stdout file, for one doc line."""
    argv = shlex.split(line, comments=True)
    stdout = None
    if ">" in argv:
        k = argv.index(">")
        stdout, argv = "{tmp}/" + argv[k + 1], argv[:k]
    assert not any(t in ("|", "&&", ";", ">>", "<") for t in argv), f"not a single command: {line}"
    sub = argv[1] if len(argv) > 1 else ""

    def redirect(opt: str, default: str) -> None:
        if opt in argv:
            k = argv.index(opt)
            argv[k + 1] = "{tmp}/" + argv[k + 1].lstrip("/")
        else:
            argv.extend([opt, "{tmp}/" + default])

    if sub in ("run", "profile", "send", "router"):
        if "--duration" in argv:
            argv[argv.index("--duration") + 1] = DURATION
        else:
            argv.extend(["--duration", DURATION])
        redirect("--out", f"out-{sub}")
        if "-q" not in argv and "--quiet" not in argv:
            argv.append("-q")
    elif sub == "keys":
        redirect("--dir", "keys")
    return argv, stdout


def commands(block: Block) -> list[str]:
    return [m.group(1) for l in block.text.splitlines() if (m := COMMAND.match(l.strip()))]


_RESULTS: dict[tuple, tuple[int, str]] = {}


def _pointflow() -> list[str]:
    exe = Path(sys.executable).with_name("pointflow")
    if exe.exists():
        return [str(exe)]
    return [sys.executable, "-c", "import sys; from pointflow.cli import main; sys.exit(main())"]


@pytest.fixture(scope="module")
def doc_tmp(tmp_path_factory):
    return tmp_path_factory.mktemp("docs-check")


@pytest.mark.parametrize("block", SHELL_BLOCKS, ids=[b.id for b in SHELL_BLOCKS])
def test_shell_block_commands_run(block: Block, doc_tmp: Path):
    _skip(block)
    for line in commands(block):
        argv, stdout = rewrite(line)
        key = (tuple(argv), stdout)
        if key not in _RESULTS:  # the same command in several docs runs once
            real = [a.replace("{tmp}", str(doc_tmp)) for a in argv]
            out_file = stdout.replace("{tmp}", str(doc_tmp)) if stdout else None
            if out_file:
                os.makedirs(os.path.dirname(out_file), exist_ok=True)
            try:
                p = subprocess.run(_pointflow() + real[1:], cwd=ROOT, capture_output=True, text=True,
                                   timeout=120, stdin=subprocess.DEVNULL)
            except subprocess.TimeoutExpired:
                _RESULTS[key] = (-1, "timed out after 120 s")
            else:
                if out_file:
                    Path(out_file).write_text(p.stdout)
                _RESULTS[key] = (p.returncode, (p.stdout[-1500:] if not out_file else "") + p.stderr[-3000:])
        code, output = _RESULTS[key]
        assert code == 0, f"{block.id}: `{line}` (run as `{' '.join(argv)}`) exited {code}:\n{output}"


# --------------------------------------------------------------------------- the check itself
def test_the_check_finds_the_blocks_it_promises():
    """Guards the parser: README's commands and YAML are among those checked."""
    readme = [b for b in BLOCKS if b.file == "README.md"]
    assert any(b.lang == "yaml" for b in readme)
    assert any("pointflow run" in c for b in readme if b in SHELL_BLOCKS for c in commands(b))
    assert all(b.skip is None or b.skip for b in BLOCKS), [b.id for b in BLOCKS if b.skip == ""]


@pytest.mark.parametrize("line,argv,stdout", [
    ("pointflow run configs/demo.yaml --duration 10 --out out   # Ctrl-C",
     ["pointflow", "run", "configs/demo.yaml", "--duration", DURATION, "--out", "{tmp}/out", "-q"], None),
    ("pointflow schema > pointflow.schema.json", ["pointflow", "schema"], "{tmp}/pointflow.schema.json"),
    ("pointflow keys robot1 --dir keys", ["pointflow", "keys", "robot1", "--dir", "{tmp}/keys"], None),
    ("pointflow send c.yaml", ["pointflow", "send", "c.yaml", "--duration", DURATION, "--out", "{tmp}/out-send", "-q"],
     None),
])
def test_commands_are_shortened_and_kept_out_of_the_clone(line, argv, stdout):
    assert rewrite(line) == (argv, stdout)


def test_prompts_are_recognised():
    assert COMMAND.match("sensor$  pointflow keys sensor --dir keys").group(1).startswith("pointflow keys")
    assert COMMAND.match("$ pointflow validate bad.yaml").group(1) == "pointflow validate bad.yaml"
    assert COMMAND.match("t=  12.0s  in=1.2M") is None
