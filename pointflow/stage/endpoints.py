"""What a stage declares of its links: one :class:`Endpoint` per ZeroMQ socket it binds,
in its own config section module (``ENDPOINTS``). The loader (pointflow/config.py) makes
``endpoints:`` from every section's declarations, so a new stage adds its links beside
its section, not in the loader."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Endpoint:
    """One link: its key under ``endpoints:`` and the socket's file in the run directory
    when the key is not set (``ipc://<run dir>/<socket>.sock``)."""

    name: str
    socket: str
    #: Who binds it and who connects, for the reader of the section.
    doc: str = ""
