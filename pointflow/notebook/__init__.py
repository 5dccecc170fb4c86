"""The notebook view (``pip install 'pointflow[notebook]'``): :class:`LiveView`, shown by
``Pipeline.show()`` and by :func:`pointflow.show` inside Jupyter (docs/views.md)."""
from __future__ import annotations

import importlib.util
import sys

__all__ = ["LiveView", "available", "in_notebook"]


def available() -> bool:
    """True when the notebook extra is installed (anywidget)."""
    return importlib.util.find_spec("anywidget") is not None


def in_notebook() -> bool:
    """True inside a Jupyter kernel (an IPython kernel app, not a terminal IPython)."""
    ip = sys.modules.get("IPython")
    try:
        shell = ip.get_ipython() if ip is not None else None
    except Exception:  # noqa: BLE001
        return False
    # a subclass counts too (Google Colab's shell is one)
    return shell is not None and any(c.__name__ == "ZMQInteractiveShell" for c in type(shell).__mro__)


def __getattr__(name: str):
    if name == "LiveView":  # anywidget is imported only when a view is made
        from .widget import LiveView

        return LiveView
    raise AttributeError(name)
