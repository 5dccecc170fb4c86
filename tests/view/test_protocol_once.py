"""The view vocabulary is written once (issue 38): the commands, the credit, the built-in
colourings and the size limits live in pointflow/render/view/protocol.py, and the view
server and the notebook take them (and everything else of render) from pointflow.render.view.
Also the client end both drive (render/view/client.py): credit, and a view opened again
when render says, by a typed field, that the view is gone."""
from __future__ import annotations

import ast
from pathlib import Path

import pointflow
from pointflow.render.view import protocol
from pointflow.render.view.client import ClientEnd

ROOT = Path(pointflow.__file__).parent
PROTOCOL = ROOT / "render" / "view" / "protocol.py"


def _modules(*pkgs: str):
    for pkg in pkgs:
        yield from sorted((ROOT / pkg).rglob("*.py"))


def _imported(path: Path) -> set[str]:
    """Absolute names of the pointflow modules ``path`` imports (relative imports resolved)."""
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    pkg = parts[:-1]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = pkg[: len(pkg) - node.level + 1] if node.level else []
            mod = ".".join(base + ([node.module] if node.module else []))
            out |= {mod} if node.module else {f"{mod}.{a.name}" for a in node.names}
    return {m for m in out if m == "pointflow" or m.startswith("pointflow.")}


def test_serve_and_notebook_import_only_render_view_of_render():
    bad = {(p.relative_to(ROOT).as_posix(), m) for p in _modules("serve", "notebook") for m in _imported(p)
           if m.startswith("pointflow.render") and not (m == "pointflow.render.view"
                                                        or m.startswith("pointflow.render.view."))}
    assert not bad, sorted(bad)


def _literals(path: Path):
    """String tuples/lists and integer constants assigned to names, in ``path``."""
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree):
        if isinstance(node, (ast.Tuple, ast.List)):
            vals = [e.value for e in node.elts if isinstance(e, ast.Constant) and isinstance(e.value, str)]
            if vals and len(vals) == len(node.elts):
                yield "strings", frozenset(vals)
        if isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            for t in targets:
                if isinstance(t, ast.Name):
                    yield "name", t.id


def test_vocabulary_defined_in_protocol_only():
    commands = frozenset(protocol.COMMANDS)
    found: dict[str, set[str]] = {"commands": set(), "colourings": set(), "credit": set(), "size": set()}
    for p in _modules("."):
        rel = p.relative_to(ROOT).as_posix()
        for kind, v in _literals(p):
            if kind == "strings" and v == commands:
                found["commands"].add(rel)
            elif kind == "strings" and {"z", "ingest_time"} <= v:
                found["colourings"].add(rel)
            elif kind == "name" and v in ("MAX_CREDIT", "MAX_IN_FLIGHT"):
                found["credit"].add(rel)
            elif kind == "name" and v in ("SIZE_RANGE", "MAX_VIEW_PX"):
                found["size"].add(rel)
    assert found == {k: {"render/view/protocol.py"} for k in found}, found


def test_pages_take_the_vocabulary_from_python():
    """The page and the widget get the colourings and the credit in their hello/state."""
    for js in list((ROOT / "serve" / "static").glob("*.js")) + list((ROOT / "notebook" / "static").glob("*.js")) \
            + list((ROOT / "render" / "view" / "static").glob("*.js")):
        text = js.read_text()
        assert '"ingest_time"' not in text and "'ingest_time'" not in text, js
        assert not ('"view_state"' in text and '"follow"' in text and '"visible"' in text), js


def test_serve_limits_are_the_render_stage_s():
    from pointflow.serve.config import ServeConfig, ServeLimits

    assert ServeLimits().max_view_px == protocol.MAX_VIEW_PX == protocol.SIZE_RANGE[1]
    from pointflow.typed import ConfigError, load_dataclass

    try:
        load_dataclass(ServeConfig, {"limits": {"max_view_px": protocol.MAX_VIEW_PX + 1}}, "serve")
    except ConfigError as exc:
        assert "max_view_px" in str(exc)
    else:
        raise AssertionError("a view larger than the render stage draws was taken")


def test_gone_is_a_field_not_a_text():
    gone = protocol.gone_reply("w1", 3)
    assert protocol.is_gone(gone) and gone["view"] == "w1" and gone["req"] == 3
    # an error that merely says so in its text is not taken for a gone view
    assert not protocol.is_gone({"type": "error", "key": "view", "error": "view: unknown view"})


def test_client_end_credit_and_reopen():
    end = ClientEnd(640, 400)
    assert end.open() == {"cmd": "open", "width": 640, "height": 400}
    assert end.credit(0) == {"cmd": "credit", "n": protocol.MAX_CREDIT}
    assert end.credit(0) is None  # unchanged: not said again
    assert end.credit(0, again=True) == {"cmd": "credit", "n": protocol.MAX_CREDIT}
    assert end.credit(1) == {"cmd": "credit", "n": protocol.MAX_CREDIT - 1}
    assert end.credit(0, withhold=True) == {"cmd": "credit", "n": 0}
    assert end.from_render({"type": "frame", "view": "w", "seq": 7}) == "frame"
    assert end.from_render({"type": "frame", "view": "w", "seq": 5}) == "frame"
    cam = {"mode": "fixed", "eye": [1.0, 2.0, 3.0], "target": [0.0, 0.0, 0.0]}
    assert end.from_render({"type": "reply", "view": "w", "camera": cam}) == "other"
    assert end.resize(640, 400) is None
    assert end.resize(320, 200) == {"cmd": "resize", "width": 320, "height": 200}
    assert end.from_render(protocol.gone_reply("w", None)) == "gone"
    again = end.open(again=True, seen=9)
    assert again == {"cmd": "open", "width": 320, "height": 200, "seq": 9, "state": {"camera": cam}}
    assert end.open(again=True)["seq"] == 7  # past every frame render sent
