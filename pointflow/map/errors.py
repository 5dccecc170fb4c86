"""The one error a map file raises: a bad file, a broken hierarchy, no room for its index."""
from __future__ import annotations


class MapError(ValueError):
    """One line naming the file and what is wrong with it."""

    def __init__(self, path: str, message: str):
        super().__init__(f"{path}: {message}")
        self.path = path
