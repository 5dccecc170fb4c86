"""The level-of-detail index of a LAS/LAZ/PLY/PCD file: an octree whose inner nodes hold a
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
import struct
import sys
import time
from typing import Callable, Iterator, Optional

import numpy as np

from .errors import MapError

log = logging.getLogger(__name__)

#: Bumped whenever the index layout or the build's choices change: old indexes are rebuilt.
INDEX_VERSION = 1
GRID_BITS = 7              # an inner node's grid: 128 cells a side
LEAF_MAX = 20_000          # a node with at most this many points left is a leaf
CHUNK_POINTS = 1 << 20     # points per read
CELL_TARGET = 2_000_000    # pass 1 aims at cells of about this many points ...
MAX_L0 = 3                 # ... in at most 8^3 spill files
MAX_CELL = 8_000_000       # a cell above this is split again instead of sorted in memory
LOD_FORMATS = ("las", "laz", "ply", "pcd")


def default_cache_dir() -> str:
    """``$XDG_CACHE_HOME/pointflow/map`` (default ``~/.cache/pointflow/map``)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "pointflow", "map")


# --------------------------------------------------------------------------- progress
class ProgressLine:
    """``map: indexing NAME: 45% (12.3 M of 27.4 M points, 2.1 M points/s, ETA 7 s)`` on stderr,
    redrawn in place on a terminal (see pointflow.runtime.console), one line per 10% elsewhere."""

    def __init__(self, name: str, stream=None, min_interval_s: float = 0.5):
        from pointflow.runtime.console import is_terminal

        self.name, self.stream = name, stream if stream is not None else sys.stderr
        self.tty = is_terminal(self.stream)
        self.t0 = time.monotonic()
        self.last_t, self.last_decile = 0.0, -1
        self.min_interval_s = min_interval_s

    def __call__(self, done: int, total: int) -> None:
        now = time.monotonic()
        final = done >= total
        frac = done / total if total else 1.0
        decile = int(frac * 10)
        if not final and (now - self.last_t < self.min_interval_s or (not self.tty and decile == self.last_decile)):
            return
        self.last_t, self.last_decile = now, decile
        rate = done / max(now - self.t0, 1e-9)
        eta = (total - done) / rate if rate > 0 else float("inf")
        line = (f"map: indexing {self.name}: {frac:4.0%} ({done / 1e6:.1f} M of {total / 1e6:.1f} M points, "
                f"{rate / 1e6:.2f} M points/s, " + (f"ETA {eta:.0f} s)" if not final else f"{now - self.t0:.1f} s)"))
        if self.tty:
            from pointflow.runtime.console import CLEAR_LINE

            self.stream.write(CLEAR_LINE + line + ("\n" if final else ""))
        else:
            self.stream.write(line + "\n")
        self.stream.flush()


# --------------------------------------------------------------------------- inputs
class _Input:
    """A file as raw records: ``dtype``, ``count`` (None until read), ``chunks()``, ``positions(recs)``."""

    path: str
    dtype: np.dtype
    count: int
    bounds: tuple[np.ndarray, np.ndarray]

    def chunks(self) -> Iterator[np.ndarray]:
        raise NotImplementedError

    def positions(self, recs: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def codes(self, recs: np.ndarray, lo: np.ndarray, side: float) -> np.ndarray:
        from .kernels import morton_codes

        return morton_codes(np.ascontiguousarray(self.positions(recs)), lo, side)


def _las_error(path: str, exc: BaseException) -> MapError:
    return MapError(path, f"not a valid LAS/LAZ file ({type(exc).__name__}: {' '.join(str(exc).split())})")


class _LasInput(_Input):
    def __init__(self, path: str):
        import laspy
        from pointflow.ingest import formats

        self.path = path
        try:
            formats._precheck_las(path)
            with laspy.open(path, laz_backend=formats._laz_backend()) as f:
                formats._check_las_header(path, f.header)
                self.header = f.header
        except formats.FormatError as exc:
            raise MapError(path, str(exc).split(": ", 1)[-1]) from None
        except BaseException as exc:
            if not formats._is_las_failure(exc):
                raise
            raise _las_error(path, exc) from None
        h = self.header
        self.point_format = h.point_format
        self.dtype = h.point_format.dtype()
        self.count = int(h.point_count)
        self.scales, self.offsets = np.asarray(h.scales, np.float64), np.asarray(h.offsets, np.float64)
        self.bounds = (np.asarray(h.mins, np.float64), np.asarray(h.maxs, np.float64))
        self.header_bytes = int(h.offset_to_point_data)

    def chunks(self) -> Iterator[np.ndarray]:
        import laspy
        from pointflow.ingest import formats

        try:
            with laspy.open(self.path, laz_backend=formats._laz_backend()) as f:
                for pts in f.chunk_iterator(CHUNK_POINTS):
                    yield pts.array
        except BaseException as exc:
            if not formats._is_las_failure(exc):
                raise
            raise _las_error(self.path, exc) from None

    def positions(self, recs: np.ndarray) -> np.ndarray:
        from .lasrec import las_positions

        return las_positions(recs, self.scales, self.offsets)

    def codes(self, recs: np.ndarray, lo: np.ndarray, side: float) -> np.ndarray:
        from .kernels import morton_codes_int

        return morton_codes_int(recs["X"], recs["Y"], recs["Z"], self.scales, self.offsets, lo, side)


def table_dtype(channels: dict[str, np.ndarray], pos_dtype=np.float64) -> np.dtype:
    fields = [("x", pos_dtype), ("y", pos_dtype), ("z", pos_dtype)]
    for k, v in channels.items():
        fields.append((k, v.dtype, v.shape[1:]) if v.ndim > 1 else (k, v.dtype))
    return np.dtype(fields)


class _TableInput(_Input):
    """PLY/PCD through the project's readers (pointflow.ingest.formats): read whole, then
    indexed in chunks. Their readers hold the file in memory (a LAS/LAZ build does not)."""

    def __init__(self, path: str, fmt: str):
        from pointflow.ingest import formats

        self.path = path
        try:
            pos, ch = formats.read_points(path, fmt)
        except formats.FormatError as exc:
            raise MapError(path, str(exc).split(": ", 1)[-1]) from None
        pos = np.asarray(pos)
        self.dtype = table_dtype(ch, pos.dtype if pos.dtype in (np.float32, np.float64) else np.float64)
        rec = np.empty(pos.shape[0], self.dtype)
        rec["x"], rec["y"], rec["z"] = pos[:, 0], pos[:, 1], pos[:, 2]
        for k, v in ch.items():
            rec[k] = v
        self._rec = rec
        self.count = int(rec.shape[0])
        finite = np.isfinite(pos).all(axis=1)
        if not finite.all():
            raise MapError(path, f"{int((~finite).sum())} points have a NaN or infinite coordinate")
        self.bounds = ((pos.min(axis=0).astype(np.float64), pos.max(axis=0).astype(np.float64)) if self.count
                       else (np.zeros(3), np.zeros(3)))
        self.header_bytes = 65536

    def chunks(self) -> Iterator[np.ndarray]:
        for a in range(0, self.count, CHUNK_POINTS):
            yield self._rec[a:a + CHUNK_POINTS]

    def positions(self, recs: np.ndarray) -> np.ndarray:
        return np.column_stack([recs["x"], recs["y"], recs["z"]]).astype(np.float64)


def _fmt(path: str) -> str:
    ext = os.path.splitext(path)[1].lower().lstrip(".")
    if ext not in LOD_FORMATS:
        raise MapError(path, f"a map file must be COPC, LAS, LAZ, PLY or PCD; not {ext or 'a file without extension'!r}")
    return ext


def _open_input(path: str) -> _Input:
    fmt = _fmt(path)
    return _LasInput(path) if fmt in ("las", "laz") else _TableInput(path, fmt)


def file_identity(path: str, header_bytes: int) -> dict:
    """What keys an index to its file: size, mtime and a SHA-1 of the header (at most 1 MiB)."""
    st = os.stat(path)
    with open(path, "rb") as f:
        head = f.read(min(max(header_bytes, 375), 1 << 20))
    return {"size": st.st_size, "mtime_ns": st.st_mtime_ns, "header_sha1": hashlib.sha1(head).hexdigest()}


def _header_bytes_of(path: str) -> int:
    """Bytes of header to checksum, read without laspy (cheap: every open checks it)."""
    if _fmt(path) in ("las", "laz"):
        with open(path, "rb") as f:
            raw = f.read(100)
        if len(raw) >= 100 and raw[:4] == b"LASF":
            return struct.unpack_from("<I", raw, 96)[0]
    return 65536


# --------------------------------------------------------------------------- build
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


class _Builder:
    def __init__(self, inp: _Input, tmp: str, progress: Callable[[int, int], None]):
        from . import kernels

        self.k = kernels
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
        inp, k = self.inp, self.k
        n = inp.count
        l0 = 0
        while l0 < MAX_L0 and n > CELL_TARGET * 8 ** l0:
            l0 += 1
        spill_dir = os.path.join(self.tmp, "spill")
        os.makedirs(spill_dir)
        files: dict[int, object] = {}
        counts: dict[int, int] = {}
        shift = np.uint64(3 * (k.DMAX - l0))
        seen = 0
        try:
            for recs in _read_ahead(inp.chunks()):
                if not recs.shape[0]:
                    continue
                seen += recs.shape[0]
                if seen > n:
                    raise MapError(inp.path, f"holds more points than its header's {n}")
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


def _dtype_from_json(descr) -> np.dtype:
    def fix(d):
        return [tuple(fix(x) if isinstance(x, list) else x for x in f) if isinstance(f, list) else f for f in d]
    return np.lib.format.descr_to_dtype(fix(descr) if isinstance(descr, list) else descr)


def index_dir(path: str, cache_dir: Optional[str] = None) -> str:
    real = os.path.realpath(path)
    name = os.path.basename(real).replace(os.sep, "_")[:80]
    return os.path.join(cache_dir or default_cache_dir(), f"{hashlib.sha1(real.encode()).hexdigest()[:16]}-{name}")


def build_index(path: str, out_dir: str, progress=None) -> None:
    """Build the index of ``path`` into ``out_dir`` (replaced atomically)."""
    inp = _open_input(path)
    parent = os.path.dirname(out_dir)
    os.makedirs(parent, exist_ok=True)
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
    try:
        ident = file_identity(path, inp.header_bytes)
        b = _Builder(inp, tmp, progress)
        t0 = time.monotonic()
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


# --------------------------------------------------------------------------- reading
class LodFile:
    """A LAS/LAZ/PLY/PCD file through its index (built or rebuilt here when missing or stale)."""

    kind = "lod"

    def __init__(self, path: str, cache_dir: Optional[str] = None, progress=None):
        self.path = path
        _fmt(path)
        self.dir = index_dir(path, cache_dir)
        why = self._stale()
        if why:
            if why != "no index yet":
                log.warning("%s: rebuilding its level-of-detail index (%s)", path, why)
            build_index(path, self.dir, progress)
            why = self._stale()
            if why:
                raise MapError(path, f"its fresh level-of-detail index in {self.dir} does not check out: {why}")
        self._open()

    def _stale(self) -> Optional[str]:
        """Why the index in :attr:`dir` cannot be used (None: it can)."""
        try:
            with open(os.path.join(self.dir, "meta.json")) as f:
                meta = json.load(f)
        except FileNotFoundError:
            return "no index yet"
        except (OSError, ValueError) as exc:
            return f"its meta.json does not read: {type(exc).__name__}"
        if not isinstance(meta, dict) or meta.get("version") != INDEX_VERSION:
            return f"index format version {meta.get('version') if isinstance(meta, dict) else '?'}, this build reads {INDEX_VERSION}"
        try:
            ident = file_identity(self.path, _header_bytes_of(self.path))
        except OSError as exc:
            raise MapError(self.path, f"cannot read: {exc.strerror or exc}") from None
        if meta.get("identity") != ident:
            return "the file changed since the index was built"
        try:
            dt = _dtype_from_json(meta["dtype"])
            nodes = np.load(os.path.join(self.dir, "nodes.npy"), allow_pickle=False)
            size = os.path.getsize(os.path.join(self.dir, "points.bin"))
        except (OSError, ValueError, KeyError, TypeError) as exc:
            return f"its files do not read: {type(exc).__name__}: {exc}"
        count = int(meta.get("count", -1))
        if size != count * dt.itemsize or int(nodes["count"].sum()) != count:
            return f"its points.bin has {size} bytes for {count} points of {dt.itemsize} bytes"
        self._meta, self._dtype, self._table = meta, dt, nodes
        return None

    def _open(self) -> None:
        meta = self._meta
        self.point_count = int(meta["count"])
        self.cube_lo = np.asarray(meta["cube_lo"], np.float64)
        self.cube_side = float(meta["cube_side"])
        self.grid = 1 << int(meta["grid_bits"])
        self.bounds = (np.asarray(meta["bounds"][0], np.float64), np.asarray(meta["bounds"][1], np.float64))
        t = self._table
        self.nodes = {(int(d), int(x), int(y), int(z)): (int(o), int(c), int(c))
                      for d, x, y, z, o, c in zip(t["d"], t["x"], t["y"], t["z"], t["offset"], t["count"])}
        self._fd = os.open(os.path.join(self.dir, "points.bin"), os.O_RDONLY)
        if meta["kind"] == "las":
            inp = _LasInput(self.path)
            if inp.dtype != self._dtype:
                raise MapError(self.path, "its point format differs from its index's")
            self.point_format, self.scales, self.offsets = inp.point_format, inp.scales, inp.offsets
            from .lasrec import las_channel_names

            self.channels = las_channel_names(self.point_format)
        else:
            self.channels = [n for n in self._dtype.names if n not in ("x", "y", "z")]

    def spacing(self, depth: int) -> float:
        return self.cube_side / (1 << depth) / self.grid

    def load(self, key: tuple) -> dict[str, np.ndarray]:
        try:
            off, _, count = self.nodes[key]
        except KeyError:
            raise KeyError(f"{self.path}: no node {key}") from None
        isz = self._dtype.itemsize
        raw = os.pread(self._fd, count * isz, off * isz)
        if len(raw) != count * isz:
            raise MapError(self.path, f"node {key}: its index file {self.dir}/points.bin is cut short")
        recs = np.frombuffer(raw, self._dtype)
        if self._meta["kind"] == "las":
            from .lasrec import las_points

            return las_points(recs, self.point_format, self.scales, self.offsets)
        out = {"positions": np.column_stack([recs["x"], recs["y"], recs["z"]]).astype(np.float64)}
        for name in self.channels:
            out[name] = recs[name].copy()
        return out

    def close(self) -> None:
        fd, self._fd = getattr(self, "_fd", None), None
        if fd is not None:
            os.close(fd)
