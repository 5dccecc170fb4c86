"""Will the ring and its two slabs fit in shared memory? Checked before anything starts.

tmpfs allocates pages as they are first written, so an oversized ring is created without
complaint and fails later (SIGBUS in whichever stage first touches a page that cannot be
had) or at ``mmap`` with ENOMEM. The supervisor asks ``statvfs`` first instead.
"""
from __future__ import annotations

import os

from .layout import SHM_DIR, RingConfigError, RingLayout, data_size
from .ring import HEADER_SIZE
from .slabs import SLAB_HEADER


class RingSpaceError(RingConfigError):
    """The ring and slabs need more bytes than the shared-memory filesystem has free."""

    def __init__(self, message: str, need: int, free: int):
        super().__init__(message)
        self.need = need
        self.free = free


def shm_bytes(layout: RingLayout) -> int:
    """Bytes of the ring segment plus both slab segments for ``layout``."""
    d = data_size(layout)
    return HEADER_SIZE + d + 2 * (SLAB_HEADER + d)


def shm_free(shm_dir: str = SHM_DIR) -> int:
    st = os.statvfs(shm_dir)
    return st.f_bavail * st.f_frsize


def check_shm_space(layout: RingLayout, shm_dir: str = SHM_DIR) -> int:
    """Raise :class:`RingSpaceError` (saying how many bytes are needed and free, and how
    many points would fit) when the ring and slabs do not fit; returns the bytes needed."""
    need = shm_bytes(layout)
    try:
        free = shm_free(shm_dir)
    except OSError as exc:
        raise RingSpaceError(f"cannot check free space in {shm_dir}: {exc.strerror or exc}", need, 0) from None
    if need > free:
        one = shm_bytes(RingLayout(1, layout.channels))
        # bytes per point in all three segments together (need ~= one + per_point * (capacity - 1))
        per_point = max(1, -(-(need - one) // max(1, layout.capacity - 1)))
        fits = max(0, (free - one) // per_point + 1) if free >= one else 0
        raise RingSpaceError(
            f"{layout.capacity:,} points need {need:,} bytes of shared memory (the ring and two slabs of "
            f"{data_size(layout):,} bytes each: {per_point} bytes per point in all), but {shm_dir} has {free:,} "
            f"bytes free; lower ring.max_points (about {fits:,} fit) or enlarge {shm_dir}", need, free)
    return need
