"""The one error a map file raises: a bad file, a broken hierarchy, no room for its index."""
from __future__ import annotations

from ..errors import KeyedError


class MapError(KeyedError):
    """One line naming the file (``key``, also ``path``) and what is wrong with it."""

    @property
    def path(self) -> str:
        return self.key
