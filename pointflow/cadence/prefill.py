"""Copy the ring's changes into the next slab while the renderer is still drawing.

With ``latest_only`` the cadence takes its snapshot when the renderer reports a frame done,
and a chunk waits for that snapshot. A slab handed out every other frame lacks everything
that changed in two frames: with 1M points a second into a 1M-point ring, the whole ring.
That copy (under the ring's lock, so ingest waited too) sat between the end of one frame
and the start of the next: 20 ms at the median, and 0.1-1.1 s when the cadence was starved
of CPU on a loaded 2-core machine. Now the ticks the cadence skips while the renderer draws
copy what changed so far into the slab the next handoff will use, and the snapshot at the
frame's end copies only the last few ticks' changes.

:class:`PrefillWriter` is a :class:`~pointflow.ring.handoff.SlabWriter` whose
:meth:`~PrefillWriter.prefill` does that copy and keeps what it took from the ring (the
dirty ranges and the committed chunks' trace ids) for the next handoff, which therefore
says exactly what a handoff without the prefill would have said.
"""
from __future__ import annotations

from typing import Any

from ..ring.handoff import SlabWriter, _union
from ..ring.ring import Changes


class _StashedChanges:
    """The ring as the writer sees it: ``take_changes()`` also returns the commits a prefill
    took earlier (its dirty ranges ride in the writer's carry instead, so that they are
    not copied twice). Everything else is the ring's."""

    def __init__(self, ring):
        self._ring = ring
        self.commits: list[tuple[int, int]] = []
        self.commits_lost = False

    def take_changes(self) -> Changes:
        ch = self._ring.take_changes()
        if not self.commits and not self.commits_lost:
            return ch
        out = Changes(ch.dirty, self.commits + list(ch.commits), ch.commits_lost or self.commits_lost)
        self.commits, self.commits_lost = [], False
        return out

    def __getattr__(self, name: str) -> Any:
        return getattr(self._ring, name)


class PrefillWriter(SlabWriter):
    """A slab writer that can bring the next slab up to date between handoffs."""

    def __init__(self, ring, slabs, ready_sock, release_sock):
        self._stash = _StashedChanges(ring)
        super().__init__(self._stash, slabs, ready_sock, release_sock)
        self.stats["prefills"] = 0
        self.stats["prefilled_slots"] = 0

    def prefill(self) -> int:
        """Copy what changed in the ring into the slab the next :meth:`publish` will write
        (the free one written last); returns the slots copied (0 when both slabs are out)."""
        self.poll_releases()
        free = [i for i in (0, 1) if self._held[i] == 0]
        if not free:
            return 0
        x = self._last_written if self._last_written in free else free[0]
        before = self.stats["copied_slots"]
        ring = self._stash._ring
        with ring.lock():
            ch = ring.take_changes()
            for i in (0, 1):
                self._pending[i] = _union(self._pending[i], ch.dirty)
            self.copy_to_slab(x, self._pending[x])
        self._pending[x] = []
        self._last_written = x
        # the next handoff says what changed since the previous one: these ranges too
        self._carry = _union(self._carry, ch.dirty)
        self._stash.commits += ch.commits
        self._stash.commits_lost |= ch.commits_lost
        n = self.stats["copied_slots"] - before
        self.stats["prefills"] += 1
        self.stats["prefilled_slots"] += n
        return n
