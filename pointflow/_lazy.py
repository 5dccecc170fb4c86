"""A package's public names, imported on first use (PEP 562 ``__getattr__``).

A package face that imported its modules eagerly would make ``import pointflow.runtime.launch``
(every stage process) pay for the supervisor, and could close an import cycle; a face
built with :func:`lazy_exports` costs nothing until a name is touched. Imports nothing of
pointflow.
"""
from __future__ import annotations

import importlib
from typing import Any, Callable


def lazy_exports(package: str, names: dict[str, str]) -> Callable[[str], Any]:
    """``__getattr__`` for ``package``: ``names`` maps a public name to its module
    (relative to the package, e.g. ``".pipeline"``)."""
    def __getattr__(name: str) -> Any:
        if name in names:
            return getattr(importlib.import_module(names[name], package), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return __getattr__
