"""A ring larger than one storage binding, split into chunks of slots and walked in segments.

A device binds at most ``max_storage_buffer_binding_size`` bytes per storage buffer (128 MiB
on lavapipe: 11,184,810 positions of 12 B). The tier therefore keeps the ring's slots in
``chunks``: consecutive slot ranges of at most ``chunk_len`` slots, each with its own buffers,
``chunk_len`` chosen so that the widest per-slot array of the raster method fits one binding.
A frame walks the ring's logical indices (oldest first) as ``segments``: runs of consecutive
slots inside one chunk, in logical order. With one chunk there is one segment, the whole ring
(its wrap handled in the shaders as before); with several, the chunk that holds the head is
walked twice (from the head to its end first, from its start to the head last). Every pass
runs once per segment with that segment's ``Params`` record; ``logical_base``, ``slot_base``
and ``group_base`` keep depth keys, hashes, LOD strides and budget ranks those of the whole
ring, so the image is the one a single binding would give.
"""
from __future__ import annotations

from dataclasses import dataclass

#: chunk lengths are multiples of this (binding windows stay aligned)
ALIGN_SLOTS = 256
#: per-chunk output windows of a second segment start at a multiple of this many entries
#: (32 x 8 B = 256 B: the largest min_storage_buffer_offset_alignment WebGPU allows)
OUT_ALIGN = 32


@dataclass
class Segment:
    """One run of slots a frame walks; fields as the segment's ``Params`` record holds them."""
    index: int          #: position in the frame's list (= logical order)
    chunk: int          #: chunk whose buffers hold the slots
    head: int           #: first slot, relative to the chunk's start
    size: int           #: slots walked
    capacity: int       #: the chunk's slot count (``slot_of`` wraps there: one chunk only)
    slot_base: int      #: first slot of the chunk in the ring
    logical_base: int   #: logical index of the segment's first slot
    out_off: int = 0    #: first entry of the segment's window in the chunk's output buffers
    groups: int = 1
    gx: int = 1
    gy: int = 1
    group_base: int = 0


def chunk_len(limit_bytes: int, bytes_per_slot: int, pad_slots: int, max_dispatch: int) -> int:
    """Slots per chunk: the widest per-slot array (``bytes_per_slot``, plus ``pad_slots``
    entries of slack) within ``limit_bytes`` and within ``max_dispatch`` threads, a multiple
    of :data:`ALIGN_SLOTS`; 0 when not even one aligned run fits."""
    n = min(int(limit_bytes) // int(bytes_per_slot) - int(pad_slots), int(max_dispatch))
    return max(n // ALIGN_SLOTS * ALIGN_SLOTS, 0)


def chunks(capacity: int, clen: int) -> list[tuple[int, int]]:
    """(first slot, slot count) of each chunk of a ring of ``capacity`` slots."""
    cap = max(int(capacity), 1)
    if cap <= clen:
        return [(0, cap)]
    return [(a, min(clen, cap - a)) for a in range(0, cap, clen)]


def segments(head: int, size: int, capacity: int, drawn_slots: int, table: list[tuple[int, int]]) -> list[Segment]:
    """The frame's segments in logical order. ``capacity``/``head``/``size``: the frame's
    ring; ``drawn_slots``: slots the tier holds (a frame's ring may be larger than the tier
    was built for: slots beyond are skipped, as one binding skipped them); ``table``: chunks."""
    cap = max(int(capacity), 1)
    size = min(int(size), cap)
    if len(table) == 1:  # the whole ring in one binding: one segment, wrapping in the shaders
        return [Segment(0, 0, int(head) % cap, size, cap, 0, 0)]
    clen = table[0][1]
    out: list[Segment] = []
    used: dict[int, int] = {}
    s, left, logical = int(head) % cap, size, 0
    while left > 0:
        if s >= drawn_slots:  # beyond the tier's slots: walked, not drawn
            n = min(cap - s, left)
        else:
            c = s // clen
            a, length = table[c]
            n = min(min(a + length, cap, drawn_slots) - s, left)
            off = used.get(c, 0)
            out.append(Segment(len(out), c, s - a, n, length, a, logical, out_off=off))
            used[c] = off + (n + OUT_ALIGN - 1) // OUT_ALIGN * OUT_ALIGN
        left -= n
        logical += n
        s = (s + n) % cap
    if not out:  # an empty ring still clears the image
        out.append(Segment(0, 0, 0, 0, table[0][1], 0, 0))
    return out


def runs(segs: list[Segment], cut_first: "list[int]", cut_len: "list[int]", first_index: int,
         room: "list[int]") -> "list[Segment] | None":
    """The frame's segments less the culled logical ranges ``[cut_first[i], cut_first[i] +
    cut_len[i])`` (whole batches, ascending, disjoint): runs of consecutive slots in logical
    order, numbered from ``first_index`` (their Params and state windows follow the segments'),
    each with its window in its chunk's output buffers; ``None`` when those windows would not
    fit the chunk's ``room`` entries (the frame is then drawn without culling). A run keeps
    its logical index (``logical_base``) and slots, so depth keys, hashes, LOD strides and
    budget ranks are those of the whole ring; a run of a single chunk may wrap its end
    (``head + size > capacity``), as the one segment does."""
    cuts = list(zip((int(a) for a in cut_first), (int(a) + int(n) for a, n in zip(cut_first, cut_len))))
    out: list[Segment] = []
    used: dict[int, int] = {}

    def emit(g: Segment, a: int, b: int) -> bool:
        off = used.get(g.chunk, 0)
        if off + (b - a) > room[g.chunk]:
            return False
        out.append(Segment(first_index + len(out), g.chunk, (g.head + a - g.logical_base) % g.capacity, b - a,
                           g.capacity, g.slot_base, a, out_off=off))
        used[g.chunk] = off + (b - a + OUT_ALIGN - 1) // OUT_ALIGN * OUT_ALIGN
        return True

    i = 0
    for g in segs:
        lo, hi = g.logical_base, g.logical_base + g.size
        at = lo
        while i < len(cuts) and cuts[i][1] <= at:
            i += 1
        j = i
        while j < len(cuts) and cuts[j][0] < hi:
            c0, c1 = cuts[j]
            if c0 > at and not emit(g, at, c0):
                return None
            at = max(at, c1)
            if c1 > hi:
                break
            j += 1
        if at < hi and not emit(g, at, hi):
            return None
    if not out:  # everything culled: one empty run (the passes still run, drawing nothing)
        out.append(Segment(first_index, segs[0].chunk, segs[0].head, 0, segs[0].capacity, segs[0].slot_base, 0))
    return out
