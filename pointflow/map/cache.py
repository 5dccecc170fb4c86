"""A bounded cache of decoded nodes: least recently used first out, bytes counted exactly."""
from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any, Hashable, Optional


def node_bytes(value: Any) -> int:
    """Bytes held by a decoded node (a dict of numpy arrays)."""
    if isinstance(value, dict):
        return sum(int(getattr(v, "nbytes", 0)) for v in value.values())
    return int(getattr(value, "nbytes", 0))


class NodeCache:
    """LRU of decoded nodes within ``max_bytes``. A node bigger than the whole cache is not
    kept (counted in ``too_big``); the caller still has it. Thread-safe: loads run in workers."""

    def __init__(self, max_bytes: int):
        if max_bytes <= 0:
            raise ValueError(f"NodeCache max_bytes must be > 0, got {max_bytes}")
        self.max_bytes = int(max_bytes)
        self._items: OrderedDict[Hashable, tuple[Any, int]] = OrderedDict()
        self._lock = threading.Lock()
        self.bytes_used = 0
        self.hits = self.misses = self.evictions = self.too_big = 0

    def get(self, key: Hashable) -> Optional[Any]:
        with self._lock:
            item = self._items.get(key)
            if item is None:
                self.misses += 1
                return None
            self._items.move_to_end(key)
            self.hits += 1
            return item[0]

    def __contains__(self, key: Hashable) -> bool:
        with self._lock:
            return key in self._items

    def __len__(self) -> int:
        return len(self._items)

    def keys(self) -> list:
        with self._lock:
            return list(self._items)

    def put(self, key: Hashable, value: Any, nbytes: Optional[int] = None) -> bool:
        """Keep ``value`` (evicting the least recently used); False when it alone exceeds the cache."""
        size = node_bytes(value) if nbytes is None else int(nbytes)
        with self._lock:
            old = self._items.pop(key, None)
            if old is not None:
                self.bytes_used -= old[1]
            if size > self.max_bytes:
                self.too_big += 1
                return False
            self._items[key] = (value, size)
            self.bytes_used += size
            while self.bytes_used > self.max_bytes:
                _, (_, s) = self._items.popitem(last=False)
                self.bytes_used -= s
                self.evictions += 1
            return True

    def evict(self, key: Hashable) -> bool:
        with self._lock:
            item = self._items.pop(key, None)
            if item is None:
                return False
            self.bytes_used -= item[1]
            self.evictions += 1
            return True

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self.bytes_used = 0

    def stats(self) -> dict:
        with self._lock:
            return {"nodes": len(self._items), "bytes": self.bytes_used, "max_bytes": self.max_bytes,
                    "hits": self.hits, "misses": self.misses, "evictions": self.evictions, "too_big": self.too_big}
