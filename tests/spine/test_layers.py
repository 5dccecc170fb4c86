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
            # ``from . import x`` imports the module x, not the package's face
            names = ([] if node.module is None and node.level else [prefix]) + [f"{prefix}.{a.name}" for a in node.names]
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


# Layers, low to high: a module imports its own layer or lower ones. Most specific prefix
# wins; a module not named takes its package's layer.
LAYERS = {
    # the bottom: the typed loader, the chunk, its wire format and codecs
    "pointflow.typed": 0, "pointflow._lazy": 0, "pointflow.chunk": 0, "pointflow.codec": 0, "pointflow.wire": 0,
    # numba's cache of the compiled loops (render and frames use it; imports nothing of pointflow)
    "pointflow.jitcache": 0,
    # shared data structures
    "pointflow.ring": 1, "pointflow.frames": 1, "pointflow.profiling": 1,
    # config sections of the packages above the loader, each owned by its package, which
    # the loader assembles (ring/config.py and frames/config.py sit in their own layer)
    "pointflow.record.config": 2, "pointflow.ingest.config": 2, "pointflow.ingest.playback": 2,
    "pointflow.cadence.config": 2, "pointflow.runtime.config": 2, "pointflow.map.config": 2,
    "pointflow.serve.config": 2, "pointflow.remote.options": 2, "pointflow.remote.keys": 2,
    "pointflow.remote.zenoh_options": 2, "pointflow.render.config": 2, "pointflow.render.view.protocol": 2,
    "pointflow.render.camera": 2,
    "pointflow.render.colormap": 2,
    # the loader, the schema, the top-level assembly
    "pointflow.config": 3,
    # what a stage is and what every stage process shares
    "pointflow.runtime.kinds": 4, "pointflow.runtime.stage": 4, "pointflow.runtime.launch": 4,
    "pointflow.runtime.rundir": 4, "pointflow.runtime.console": 4,
    # the stages
    "pointflow.ingest": 5, "pointflow.cadence": 5, "pointflow.render": 5, "pointflow.record": 5,
    "pointflow.remote": 5, "pointflow.serve": 5,
    # the notebook view: a client of the render stage's views, beside the view server
    "pointflow.notebook": 5,
    # the map library reads files with ingest's readers; its stage draws through render
    "pointflow.map": 5,
    # running them: lifecycle, accounting, liveness, the Python API
    "pointflow.runtime": 6,
    # faces: the command line, the client, quick views, the package itself
    "pointflow.client": 7, "pointflow.quickshow": 7, "pointflow.cli": 7, "pointflow": 7,
}
#: The one import upward: the config loader resolves transports (the registry) to check
#: their options with their own schema.
UPWARD_ALLOWED = {("pointflow.config", "pointflow.ingest.transports")}


def _layer(mod: str) -> int:
    m = mod
    while m not in LAYERS:
        m = m.rpartition(".")[0]
    return LAYERS[m]


def test_no_module_imports_a_layer_above_it():
    """Imports run one way (issue 27): no module imports a package above it, other than
    the config loader's transport registry."""
    g = _graph()
    bad = sorted((m, d) for m, deps in g.items() for d in deps
                 if d != "pointflow" and _layer(d) > _layer(m) and (m, d) not in UPWARD_ALLOWED)
    assert not bad, "upward imports: " + ", ".join(f"{m} -> {d}" for m, d in bad)
