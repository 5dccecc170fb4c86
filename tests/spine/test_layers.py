"""Imports run one way: the package's module import graph has no cycle (issue 14.8:
config ↔ ingest.transports was one), and the typed loader sits at the bottom."""
from __future__ import annotations

import ast
from pathlib import Path

import pointflow

ROOT = Path(pointflow.__file__).parent


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports(path: Path, mod: str, known: set[str]) -> set[str]:
    """pointflow modules imported by ``path`` anywhere (top level or inside functions)."""
    is_pkg = path.name == "__init__.py"
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = mod.split(".")
                base = base[: len(base) - node.level + (1 if is_pkg else 0)]
                prefix = ".".join(base + ([node.module] if node.module else []))
            else:
                prefix = node.module or ""
            names = [prefix] + [f"{prefix}.{a.name}" for a in node.names]
        else:
            continue
        for n in names:
            # the longest known module the name refers to
            while n and n not in known:
                n = n.rpartition(".")[0]
            if n and n != mod:
                out.add(n)
    return out


def _graph() -> dict[str, set[str]]:
    files = {_module_name(p): p for p in ROOT.rglob("*.py")}
    known = set(files)
    return {m: _imports(p, m, known) for m, p in files.items()}


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        stack.append(m)
        for d in sorted(graph.get(m, ())):
            # a package importing its own submodules is how packages re-export
            if d.startswith(m + "."):
                continue
            if state.get(d) == 1:
                return stack[stack.index(d):] + [d]
            if d not in state:
                found = visit(d)
                if found:
                    return found
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state:
            found = visit(m)
            if found:
                return found
    return None


def test_no_import_cycle():
    cyc = _cycle(_graph())
    assert cyc is None, "import cycle: " + " -> ".join(cyc)


def test_transports_do_not_import_config():
    g = _graph()
    offenders = {m for m, deps in g.items() if m.startswith("pointflow.ingest.transports") and "pointflow.config" in deps}
    assert not offenders


def test_typed_loader_is_the_bottom_layer():
    assert not _graph()["pointflow.typed"], "pointflow.typed must import nothing of pointflow"


def test_no_render_tier_imports_another_tier():
    """The shared draw rules live in render/rules.py; a tier never borrows them from another."""
    tiers = {"cpu": "pointflow.render.cpu", "gl": "pointflow.render.gl", "wgpu": "pointflow.render.wgpu_tier"}
    g = _graph()
    offenders = {(m, d) for m, deps in g.items() for d in deps
                 for t, root in tiers.items() for u, other in tiers.items()
                 if t != u and (m == root or m.startswith(root + ".")) and (d == other or d.startswith(other + "."))}
    assert not offenders, sorted(offenders)
    assert "pointflow.render.rules" in g["pointflow.render.cpu"] and "pointflow.render.rules" in g["pointflow.render.gl"]
    assert "pointflow.render.rules" in g["pointflow.render.wgpu_tier.reference"]
