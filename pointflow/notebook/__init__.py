"""The notebook view (``pip install 'pointflow[notebook]'``): :class:`LiveView`, shown by
``Pipeline.show()`` and by :func:`pointflow.show` inside Jupyter (docs/views.md)."""
from __future__ import annotations

import importlib.util

__all__ = ["LiveView", "available"]


def available() -> bool:
    """True when the notebook extra is installed (anywidget)."""
    return importlib.util.find_spec("anywidget") is not None


def __getattr__(name: str):
    if name == "LiveView":  # anywidget is imported only when a view is made
        from .widget import LiveView

        return LiveView
    raise AttributeError(name)
