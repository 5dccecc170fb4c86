"""The map layer's library: big static clouds read by level of detail.

``open_map(paths)`` gives a :class:`MapSource` over COPC files (read through their own
hierarchy) and LAS/LAZ/PLY/PCD files (a level-of-detail index built once and cached);
:func:`select_nodes` picks the nodes a camera needs within a point budget; :class:`NodeCache`
keeps decoded nodes within a byte bound. Import-light: laspy and numba load on first use.
"""
from __future__ import annotations

from .cache import NodeCache
from .errors import MapError
from .select import select_nodes
from .source import MapNode, MapSource, open_map

__all__ = ["MapError", "MapNode", "MapSource", "NodeCache", "open_map", "select_nodes"]
