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


def test_no_stage_imports_the_config_loader():
    """The loader assembles the stages' sections, so it sits above them (issue 38.5): a
    stage gets its config in its context and imports only its own section."""
    stages = ("ingest", "cadence", "render", "record", "remote", "serve", "notebook", "map", "formats", "stage")
    g = _graph()
    offenders = sorted(m for m, deps in g.items() if "pointflow.config" in deps
                       and any(m == f"pointflow.{s}" or m.startswith(f"pointflow.{s}.") for s in stages))
    assert not offenders, offenders


def test_typed_loader_is_the_bottom_layer():
    g = _graph()
    # the error root (ConfigError is a pointflow.errors.KeyedError) is the one floor below it
    assert g["pointflow.typed"] <= {"pointflow.errors"}, "pointflow.typed must import nothing of pointflow but errors"
    assert not g["pointflow.errors"], "pointflow.errors must import nothing of pointflow"


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
    # the bottom: the typed loader, the error root, the chunk, its wire format and codecs
    "pointflow.typed": 0, "pointflow._lazy": 0, "pointflow.errors": 0, "pointflow.chunk": 0, "pointflow.codec": 0,
    "pointflow.wire": 0,
    # numba's cache of the compiled loops (render and frames use it; imports nothing of pointflow)
    "pointflow.jitcache": 0,
    # reductions over (n, 3) point arrays column by column (imports nothing of pointflow)
    "pointflow.arrays": 0,
    # shared data structures and the point-file readers
    "pointflow.ring": 1, "pointflow.frames": 1, "pointflow.profiling": 1, "pointflow.formats": 1,
    # the stage kit: what a stage is and what every stage process shares (context, kinds,
    # counters, endpoints, console), below every stage and its config section
    "pointflow.stage": 2,
    # config sections of the packages above the loader, each owned by its package (with the
    # endpoints its stage binds), which the loader assembles (ring/config.py and
    # frames/config.py sit in their own layer)
    "pointflow.record.config": 3, "pointflow.ingest.config": 3, "pointflow.ingest.playback": 3,
    "pointflow.cadence.config": 3, "pointflow.map.config": 3,
    "pointflow.serve.config": 3, "pointflow.remote.options": 3, "pointflow.remote.keys": 3,
    "pointflow.remote.zenoh_options": 3, "pointflow.render.config": 3, "pointflow.render.view.protocol": 3,
    "pointflow.render.camera": 3,
    "pointflow.render.colormap": 3,
    # the stages
    "pointflow.ingest": 4, "pointflow.cadence": 4, "pointflow.render": 4, "pointflow.record": 4,
    "pointflow.remote": 4, "pointflow.serve": 4,
    # the notebook view: a client of the render stage's views, beside the view server
    "pointflow.notebook": 4,
    # the map library reads files with the readers of pointflow.formats; its stage draws through render
    "pointflow.map": 4,
    # the loader, the schema, the top-level assembly of the stages' sections: above the
    # stages (no stage imports it; a stage's loop gets its config in its context)
    "pointflow.config": 5,
    # running them: lifecycle, launch, accounting, liveness, the Python API
    "pointflow.runtime": 6,
    # faces: the command line, the client, quick views, the package itself
    "pointflow.connect": 7, "pointflow.show": 7, "pointflow.cli": 7, "pointflow": 7,
    # test rigs shipped with the package: they drive the stages and the runtime
    "pointflow.testing": 7,
}
#: No import runs upward.
UPWARD_ALLOWED: set[tuple[str, str]] = set()


def _layer(mod: str) -> int:
    m = mod
    while m not in LAYERS:
        m = m.rpartition(".")[0]
    return LAYERS[m]


def test_no_module_imports_a_layer_above_it():
    """Imports run one way (issue 27, 38): no module imports a package above it."""
    g = _graph()
    bad = sorted((m, d) for m, deps in g.items() for d in deps
                 if d != "pointflow" and _layer(d) > _layer(m) and (m, d) not in UPWARD_ALLOWED)
    assert not bad, "upward imports: " + ", ".join(f"{m} -> {d}" for m, d in bad)
