"""Building the level-of-detail index of a LAS/LAZ/PLY/PCD file: an octree whose inner nodes hold a
spread-out subset of their subtree's points (one point per cell of a 128^3 grid of the node,
as Potree's converter does), built once and kept in the user cache directory.

The build reads the file once, in chunks, and never holds more than one cell of it in
memory: pass 1 sorts each chunk's raw records into spill files, one per cell of the octree at
depth ``L0`` (<= 512 files); pass 2 builds each cell's subtree in memory (one sort by Morton
code, one compiled sweep per depth) and writes its nodes, keeping back the cell's root
points; the top ``L0`` depths are then chosen from those. A cell too big for memory is split
again the same way. Every point is in exactly one node.

The index stores the file's own records (LAS: laspy's packed point records; PLY/PCD: the
file's fields), so a loaded node is exactly the file's points. It is keyed by the file's
size, mtime and a checksum of its header, and by :data:`INDEX_VERSION`; a mismatch rebuilds.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import time
from typing import Callable, Iterator, Optional

import numpy as np

from ..errors import Error
from .errors import MapError
from .inputs import CHUNK_POINTS, _Input, _LasInput, file_identity, open_input
from .progress import ProgressLine

log = logging.getLogger(__name__)

#: Bumped whenever the index layout or the build's choices change: old indexes are rebuilt.
INDEX_VERSION = 1
GRID_BITS = 7              # an inner node's grid: 128 cells a side
LEAF_MAX = 20_000          # a node with at most this many points left is a leaf
CELL_TARGET = 2_000_000    # pass 1 aims at cells of about this many points ...
MAX_L0 = 3                 # ... in at most 8^3 spill files
MAX_CELL = 8_000_000       # a cell above this is split again instead of sorted in memory


def default_cache_dir() -> str:
    """``$XDG_CACHE_HOME/pointflow/map`` (default ``~/.cache/pointflow/map``)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "pointflow", "map")


def _read_ahead(chunks: Iterator[np.ndarray], depth: int = 2) -> Iterator[np.ndarray]:
    """The chunks, read (LAZ: decompressed, lazrs releases the GIL) by a thread up to ``depth``
    chunks ahead of the indexing, so on two cores the two overlap. An error in the reader is
    raised here; leaving early stops the reader."""
    import queue
    import threading

    q: queue.Queue = queue.Queue(depth)
    stop = threading.Event()
    end = object()

    def work() -> None:
        try:
            for c in chunks:
                while not stop.is_set():
                    try:
                        q.put(c, timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            q.put(end)
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer
            q.put(exc)

    t = threading.Thread(target=work, name="map-index-read", daemon=True)
    t.start()
    try:
        while True:
            item = q.get()
            if item is end:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        while t.is_alive():
            try:
                q.get_nowait()
            except queue.Empty:
                pass
            t.join(0.05)


def gather(recs: np.ndarray, perm: np.ndarray) -> np.ndarray:
    """``recs[perm]`` through a field-less view: numpy gathers plain void items with one copy
    each, structured ones field by field (about 10x slower for LAS records)."""
    return recs.view(np.dtype((np.void, recs.dtype.itemsize)))[perm].view(recs.dtype)


class _WrongBounds(Error):
    """The header's bounds do not hold the points (seen: their real bounds)."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray):
        super().__init__("points outside the header's bounds")
        self.lo, self.hi = lo, hi


class _Builder:
    def __init__(self, inp: _Input, tmp: str, progress: Callable[[int, int], None], preview=None,
                 preview_points: int = 0):
        self.inp, self.tmp, self.progress = inp, tmp, progress
        lo, hi = inp.bounds
        ext = float(np.max(hi - lo)) if inp.count else 0.0
        side = ext * (1 + 1e-6) if ext > 0 else 1.0
        self.lo = (lo + hi) / 2 - side / 2
        self.side = side
        self.itemsize = inp.dtype.itemsize
        self.data = open(os.path.join(tmp, "points.bin"), "wb")
        self.written = 0
        self.node_parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self.total_units = 2 * max(inp.count, 1)
        self.done_units = 0
        self.preview = preview  # called with an evenly spread share of each chunk read, decoded
        self.preview_stride = max(1, -(-max(inp.count, 1) // max(preview_points, 1)))

    @property
    def k(self):
        """The compiled kernels, imported on first use: numba's import takes seconds on a loaded
        machine, and the first chunk's preview should not wait for it."""
        from . import kernels

        return kernels

    def _tick(self, n: int) -> None:
        self.done_units += n
        total = self.total_units // 2
        self.progress(min(self.done_units // 2, total - 1), total)  # 100% once, when the index is in place

    def codes(self, recs: np.ndarray) -> np.ndarray:
        return self.inp.codes(recs, self.lo, self.side)

    def place(self, recs: np.ndarray, codes: np.ndarray, order: Optional[np.ndarray], l_start: int, l_stop: int,
              leaf_max: int) -> tuple[np.ndarray, np.ndarray]:
        """Give the points (``codes`` sorted, ``recs`` in ``order``) their depths, write every
        node deeper than ``l_start``, return the points of depth ``l_start`` (recs, codes).
        One gather of the records: by (depth, code), the order the nodes are written in."""
        lvl = self.k.assign_levels(codes, l_start, l_stop, leaf_max, GRID_BITS, np.full(codes.shape[0], -1, np.int8))
        by_depth = np.argsort(lvl, kind="stable")  # int8: a radix sort; codes stay sorted within a depth
        perm = by_depth if order is None else order[by_depth]
        recs, codes, lvl = gather(recs, perm), codes[by_depth], lvl[by_depth]
        n_top = int(np.searchsorted(lvl, l_start, side="right"))
        self.write_nodes(recs[n_top:], codes[n_top:], lvl[n_top:])
        return recs[:n_top].copy(), codes[:n_top].copy()

    def write_nodes(self, recs: np.ndarray, codes: np.ndarray, lvl: np.ndarray) -> None:
        """Write points already in (depth, code) order, one run per node."""
        if not recs.shape[0]:
            return
        lvl = lvl.astype(np.int64)
        prefix = codes >> (np.uint64(3) * (np.uint64(self.k.DMAX) - lvl.astype(np.uint64)))
        cut = np.flatnonzero((lvl[1:] != lvl[:-1]) | (prefix[1:] != prefix[:-1])) + 1
        starts = np.concatenate([[0], cut])
        counts = np.diff(np.concatenate([starts, [recs.shape[0]]]))
        recs.tofile(self.data)
        self.node_parts.append((lvl[starts].astype(np.int8), prefix[starts], starts + self.written, counts))
        self.written += recs.shape[0]

    def run(self) -> None:
        inp = self.inp
        n = inp.count
        l0 = 0
        while l0 < MAX_L0 and n > CELL_TARGET * 8 ** l0:
            l0 += 1
        spill_dir = os.path.join(self.tmp, "spill")
        os.makedirs(spill_dir)
        files: dict[int, object] = {}
        counts: dict[int, int] = {}
        seen = 0
        lo_seen, hi_seen = np.full(3, np.inf), np.full(3, -np.inf)
        try:
            for recs in _read_ahead(inp.chunks()):
                if not recs.shape[0]:
                    continue
                seen += recs.shape[0]
                if seen > n:
                    raise MapError(inp.path, f"holds more points than its header's {n}")
                if self.preview is not None:
                    self.preview(inp.decode(recs[::self.preview_stride]))
                k = self.k
                shift = np.uint64(3 * (k.DMAX - l0))
                clo, chi = inp.chunk_bounds(recs)
                lo_seen, hi_seen = np.minimum(lo_seen, clo), np.maximum(hi_seen, chi)
                cell = (self.codes(recs) >> shift).astype(np.int64)
                perm, starts = k.bucket_order(cell, 8 ** l0)
                recs = gather(recs, perm)
                for c in np.flatnonzero(np.diff(starts)):
                    a, b = int(starts[c]), int(starts[c + 1])
                    c = int(c)
                    fh = files.get(c)
                    if fh is None:
                        fh = files[c] = open(os.path.join(spill_dir, f"c{c}.bin"), "wb")
                    recs[a:b].tofile(fh)
                    counts[c] = counts.get(c, 0) + int(b - a)
                self._tick(recs.shape[0])
        finally:
            for fh in files.values():
                fh.close()
        if seen != n:
            raise MapError(inp.path, f"header promises {n} points, the file holds {seen} (truncated?)")
        tol = float(np.max(np.abs(getattr(inp, "scales", np.zeros(3))))) + 1e-9
        if n and (np.any(lo_seen < inp.bounds[0] - tol) or np.any(hi_seen > inp.bounds[1] + tol)):
            raise _WrongBounds(lo_seen, hi_seen)
        pend_recs, pend_codes = [], []
        for c in sorted(counts):
            r, cd = self.cell(os.path.join(spill_dir, f"c{c}.bin"), l0, counts[c])
            pend_recs.append(r)
            pend_codes.append(cd)
        if pend_recs:
            recs, codes = np.concatenate(pend_recs), np.concatenate(pend_codes)
            if l0 == 0:
                self.write_nodes(recs, codes, np.zeros(codes.shape[0], np.int8))
            else:
                recs, codes = self.place(recs, codes, None, 0, l0, -1)
                self.write_nodes(recs, codes, np.zeros(codes.shape[0], np.int8))
        self.data.close()

    def cell(self, spill: str, level: int, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Build the subtree of one spill file; return its root's points (not written yet)."""
        k = self.k
        if n > MAX_CELL and level < k.DMAX - 1:
            return self.split(spill, level, n)
        recs = np.fromfile(spill, self.inp.dtype)
        os.unlink(spill)
        if recs.shape[0] != n:
            raise MapError(self.inp.path, f"index build: spill file {spill} holds {recs.shape[0]} of {n} points")
        codes = self.codes(recs)
        order = np.argsort(codes)
        out = self.place(recs, codes[order], order, level, k.DMAX + 1, LEAF_MAX)
        self._tick(n)
        return out

    def split(self, spill: str, level: int, n: int) -> tuple[np.ndarray, np.ndarray]:
        k = self.k
        shift = np.uint64(3 * (k.DMAX - level - 1))
        base = spill[:-4]
        fhs = [open(f"{base}_{i}.bin", "wb") for i in range(8)]
        counts = [0] * 8
        try:
            for a in range(0, n, CHUNK_POINTS):
                recs = np.fromfile(spill, self.inp.dtype, count=min(CHUNK_POINTS, n - a), offset=a * self.itemsize)
                child = ((self.codes(recs) >> shift) & np.uint64(7)).astype(np.uint8)
                for i in range(8):
                    sel = recs[child == i]
                    sel.tofile(fhs[i])
                    counts[i] += sel.shape[0]
        finally:
            for fh in fhs:
                fh.close()
        os.unlink(spill)
        pend = [self.cell(f"{base}_{i}.bin", level + 1, counts[i]) for i in range(8) if counts[i]]
        for i in range(8):
            if not counts[i]:
                os.unlink(f"{base}_{i}.bin")
        recs = np.concatenate([p[0] for p in pend])
        codes = np.concatenate([p[1] for p in pend])
        return self.place(recs, codes, None, level, level + 1, -1)

    def node_table(self) -> np.ndarray:
        dt = np.dtype([("d", np.int8), ("x", np.int32), ("y", np.int32), ("z", np.int32),
                       ("offset", np.int64), ("count", np.int64)])
        if not self.node_parts:
            return np.zeros(0, dt)
        lvl = np.concatenate([p[0] for p in self.node_parts])
        prefix = np.concatenate([p[1] for p in self.node_parts])
        out = np.empty(lvl.shape[0], dt)
        xyz = self.k.decode_prefixes(prefix)
        out["d"] = lvl
        out["x"], out["y"], out["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        out["offset"] = np.concatenate([p[2] for p in self.node_parts])
        out["count"] = np.concatenate([p[3] for p in self.node_parts])
        return out


def _dtype_to_json(dt: np.dtype):
    return np.lib.format.dtype_to_descr(dt)


def dtype_from_json(descr) -> np.dtype:
    def fix(d):
        return [tuple(fix(x) if isinstance(x, list) else x for x in f) if isinstance(f, list) else f for f in d]
    return np.lib.format.descr_to_dtype(fix(descr) if isinstance(descr, list) else descr)


def index_dir(path: str, cache_dir: Optional[str] = None) -> str:
    real = os.path.realpath(path)
    name = os.path.basename(real).replace(os.sep, "_")[:80]
    return os.path.join(cache_dir or default_cache_dir(), f"{hashlib.sha1(real.encode()).hexdigest()[:16]}-{name}")


#: This process's half-built index folders (a build in a thread of a stage that is stopping
#: leaves its folder: the stage removes it on the way out, :func:`remove_unfinished`).
_UNFINISHED: set[str] = set()


def remove_unfinished() -> list[str]:
    """Remove the folders of this process's builds still under way (the map stage, stopped
    while its index is built: a 272 MB spill folder was left until the file was opened again).
    Returns them."""
    gone = sorted(_UNFINISHED)
    for d in gone:
        shutil.rmtree(d, ignore_errors=True)
        _UNFINISHED.discard(d)
    return gone


def _remove_orphans(out_dir: str) -> None:
    """Half-built indexes (``<dir>.tmp-<pid>-...``, ``<dir>.old-<pid>-...``) of builds killed
    before they could clean up: removed when their process is gone."""
    import glob

    for d in glob.glob(glob.escape(out_dir) + ".tmp-*") + glob.glob(glob.escape(out_dir) + ".old-*"):
        try:
            pid = int(d.rsplit(".", 1)[1].split("-")[1])
        except (IndexError, ValueError):
            continue
        try:
            os.kill(pid, 0)
            continue  # still building (or another process now has its pid: left for later)
        except ProcessLookupError:
            pass
        except PermissionError:
            continue
        log.info("removing %s, left by a build that was killed", d)
        shutil.rmtree(d, ignore_errors=True)


def build_index(path: str, out_dir: str, progress=None, preview=None, preview_points: int = 0) -> None:
    """Build the index of ``path`` into ``out_dir`` (replaced atomically). ``preview``: called
    from the first pass with about ``preview_points`` of the file in all, an evenly spread share
    of each chunk as it is read (decoded as a node's load is), so a map can be drawn while its
    index is built."""
    inp = open_input(path)
    parent = os.path.dirname(out_dir)
    os.makedirs(parent, exist_ok=True)
    _remove_orphans(out_dir)
    need = int(inp.count * inp.dtype.itemsize * 1.1) + (64 << 20)
    free = shutil.disk_usage(parent).free
    if need > free:
        raise MapError(path, f"its level-of-detail index needs about {need / 2**30:.2f} GiB in {parent}, "
                             f"only {free / 2**30:.2f} GiB are free (free some space or set the map cache directory)")
    if progress is None:
        progress = ProgressLine(os.path.basename(path))
    elif progress is False:
        progress = lambda done, total: None  # noqa: E731
    tmp = f"{out_dir}.tmp-{os.getpid()}-{time.monotonic_ns()}"
    os.makedirs(tmp)
    _UNFINISHED.add(tmp)
    try:
        ident = file_identity(path, inp.header_bytes)
        t0 = time.monotonic()
        try:
            b = _Builder(inp, tmp, progress, preview, preview_points)
            b.run()
        except _WrongBounds as wb:
            b.data.close()
            log.warning("%s: its header's bounds %s..%s do not hold all its points (they span %s..%s): "
                        "indexing it again with the points' own bounds", path, inp.bounds[0].tolist(),
                        inp.bounds[1].tolist(), wb.lo.tolist(), wb.hi.tolist())
            shutil.rmtree(tmp, ignore_errors=True)
            os.makedirs(tmp)
            inp.bounds = (wb.lo, wb.hi)
            b = _Builder(inp, tmp, progress)
            b.run()
        nodes = b.node_table()
        if int(nodes["count"].sum()) != inp.count:
            raise MapError(path, f"index build placed {int(nodes['count'].sum())} of {inp.count} points")
        np.save(os.path.join(tmp, "nodes.npy"), nodes)
        shutil.rmtree(os.path.join(tmp, "spill"), ignore_errors=True)
        meta = {"version": INDEX_VERSION, "path": os.path.realpath(path), "identity": ident,
                "kind": "las" if isinstance(inp, _LasInput) else "table", "count": inp.count,
                "dtype": _dtype_to_json(inp.dtype), "cube_lo": b.lo.tolist(), "cube_side": b.side,
                "bounds": [inp.bounds[0].tolist(), inp.bounds[1].tolist()], "grid_bits": GRID_BITS,
                "leaf_max": LEAF_MAX, "nodes": int(nodes.shape[0]), "build_s": round(time.monotonic() - t0, 3)}
        with open(os.path.join(tmp, "meta.json"), "w") as f:
            json.dump(meta, f)
        progress(inp.count, inp.count)
        old = None
        if os.path.exists(out_dir):
            old = f"{out_dir}.old-{os.getpid()}-{time.monotonic_ns()}"
            os.rename(out_dir, old)
        os.rename(tmp, out_dir)
        if old:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        _UNFINISHED.discard(tmp)
