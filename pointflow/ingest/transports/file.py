"""``file``: replay point-cloud files as a stream.

Two modes:

* ``scans``: each file (a glob or a directory gives many) is one scan, released whole at
  ``rate`` scans per second (the Ouster recordings at 10 Hz); cut into pieces of at most
  ``chunk_points`` if a scan is larger.
* ``stream``: one big file cut into chunks of ``chunk_points`` released at
  ``points_per_second`` (LAS/LAZ are read piece by piece, so big files stream).

``auto`` picks ``scans`` for several files, ``stream`` for one. ``realtime: false`` sends
as fast as ingest accepts (the source waits instead of dropping: a replay is lossless).
Coordinates stay float64 (georeferenced LAS) and the format's channels come along (see
:mod:`pointflow.formats`); ``rename`` maps channel names (e.g. Ouster
``reflectivity`` -> ``intensity``). Its progress (``transport_progress``, of ``transport_total``
points) is shown on the progress line of ``pointflow run``, the one place that draws on the terminal;
the first time it sends more points than the ring holds it says so, once.
A file that cannot be read (a :class:`~pointflow.formats.FormatError`, or anything a
reader raises) is logged with the reason, counted (``transport_bad_files``) and skipped: what
was read before the defect is kept, and the other files go on. When *none* of the source's
files can be read, :class:`~.base.InputUnreadable` names them and why, and the run fails.
"""
from __future__ import annotations

import dataclasses
import glob
import logging
import os
import time
from typing import Any, Iterator, Literal, Optional

import numpy as np

from ...chunk import PointChunk
from ...typed import ConfigError
from ... import formats
from ..playback import PlaybackClock
from .base import InputUnreadable, Transport

log = logging.getLogger("pointflow.transport.file")


@dataclasses.dataclass
class FileOptions:
    #: A file, a glob (``scans/*.npz``) or a directory (all point files in it, sorted).
    path: str
    format: Literal["auto", "las", "laz", "ply", "pcd", "npy", "npz", "csv", "xyz", "txt", "bin"] = "auto"
    mode: Literal["auto", "scans", "stream"] = "auto"
    #: scans mode: scans per second.
    rate: float = 10.0
    #: stream mode: points per second.
    points_per_second: float = 1_000_000.0
    chunk_points: int = 50_000
    realtime: bool = True
    #: Replay forever.
    loop: bool = False
    #: Channel renames, e.g. {reflectivity: intensity}.
    rename: dict[str, str] = dataclasses.field(default_factory=dict)
    #: Keep only these channels (after renaming); null = all.
    channels: Optional[list[str]] = None
    #: CSV/XYZ column names when the file has no header row.
    columns: Optional[list[str]] = None
    #: The share of a one-file stream sent, on the progress line of ``pointflow run``
    #: (``transport_total`` in the source's stats); ``off``: not shown. ``auto`` = ``on``.
    progress: Literal["auto", "on", "off"] = "auto"


def _expand(path: str) -> list[str]:
    if os.path.isdir(path):
        files = [os.path.join(path, f) for f in os.listdir(path)]
        return sorted(f for f in files if os.path.splitext(f)[1].lower().lstrip(".") in formats.FORMATS)
    if any(c in path for c in "*?["):
        return sorted(glob.glob(path))
    return [path]


class FileTransport(Transport):
    name = "file"
    options_schema = FileOptions
    lossless = True
    seekable = True

    @classmethod
    def check_options(cls, o: FileOptions, path: str, base_dir: str) -> None:
        p = o.path if os.path.isabs(o.path) else os.path.join(base_dir, o.path)
        files = _expand(p)
        if not files or not all(os.path.isfile(f) for f in files):
            raise ConfigError(f"{path}.path", f"no such file(s): {o.path!r} (resolved to {p!r})")
        if o.format == "auto":
            for f in files:
                try:
                    formats.detect_format(f)
                except formats.FormatError as exc:
                    raise ConfigError(f"{path}.path", str(exc)) from None
        for key in ("rate", "points_per_second"):
            if getattr(o, key) <= 0:
                raise ConfigError(f"{path}.{key}", f"must be > 0, got {getattr(o, key)!r}")
        if o.chunk_points < 1:
            raise ConfigError(f"{path}.chunk_points", "must be >= 1")
        o.path = os.path.abspath(p)  # the source process may run elsewhere (cwd)

    #: declared_channels reads a whole file of another format only up to this size
    #: (LAS/LAZ: one point; KITTI: fixed); larger ones are known when their points arrive.
    PEEK_BYTES = 8 << 20

    @classmethod
    def declared_channels(cls, options: dict[str, Any], base_dir: str = ".") -> Optional[frozenset[str]]:
        """The first file's channels (renamed and filtered as they will be sent), when one
        format is used and it can be read cheaply; None otherwise (never an error here)."""
        o = FileOptions(**options)
        try:
            files = _expand(o.path)
            fmts = {o.format if o.format != "auto" else formats.detect_format(f) for f in files}
            if not files or len(fmts) != 1:
                return None
            fmt, f = fmts.pop(), files[0]
            if fmt in ("las", "laz"):
                names = set(next(formats.iter_las(f, 1))[1])
            elif fmt == "bin":
                names = {"intensity"}
            elif os.path.getsize(f) <= cls.PEEK_BYTES:
                names = set(formats.read(f, fmt, o.columns)[1])
            else:
                return None
        except Exception:  # noqa: BLE001 - a bad file is reported when it is read, not at load
            return None
        names = {o.rename.get(k, k) for k in names}
        return frozenset(names if o.channels is None else names & set(o.channels))

    def __init__(self, options: dict[str, Any], source_id: str):
        super().__init__(options, source_id)
        self.o = FileOptions(**options)
        self.files = _expand(self.o.path)
        self.counters = {"files": 0, "points": 0, "loops": 0, "bad_files": 0}
        #: "file: why" of each file that could not be read (for the error when none can).
        self.bad_reasons: list[str] = []
        self._unsaid: list[str] = []  # skipped before any file was read (:meth:`_bad_file`)
        self._overrun_said = False
        #: Pacing, pause, seek, step, rate (a factor on ``rate``/``points_per_second``), loop.
        self.playback = PlaybackClock(rate=1.0, loop=self.o.loop, realtime=self.o.realtime)

    def open(self) -> None:
        if not self.files:
            raise FileNotFoundError(f"file transport: no files match {self.o.path!r}")
        for f in self.files:
            if not os.path.isfile(f):
                raise FileNotFoundError(f"file transport: {f} does not exist")
        mode = self.o.mode
        if mode == "auto":
            mode = "scans" if len(self.files) > 1 else "stream"
        self.mode = mode
        self.total = None
        if mode == "stream" and len(self.files) == 1 and self._fmt(self.files[0]) in ("las", "laz"):
            try:
                self.total = formats.las_point_count(self.files[0])
            except formats.FormatError:
                self.total = None  # reported (and counted) when the file is read

    def _fmt(self, f: str) -> str:
        return self.o.format if self.o.format != "auto" else formats.detect_format(f)

    def _channels(self, ch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        out = {self.o.rename.get(k, k): v for k, v in ch.items()}
        if self.o.channels is not None:
            out = {k: v for k, v in out.items() if k in self.o.channels}
        return out

    def _pieces(self, f: str) -> Iterator[tuple[np.ndarray, dict]]:
        """A file in pieces of at most ``chunk_points``."""
        cp = self.o.chunk_points
        fmt = self._fmt(f)
        if fmt in ("las", "laz"):
            yield from formats.iter_las(f, cp)
            return
        pos, ch = formats.read(f, fmt, self.o.columns)
        n = pos.shape[0]
        if self.total is None and self.mode == "stream":
            self.total = n
        for a in range(0, max(n, 1), cp):
            yield pos[a:a + cp], {k: v[a:a + cp] for k, v in ch.items()}

    def _bad_file(self, f: str, exc: Exception) -> None:
        """Count and log a file that cannot be read (the rest of it and the next files go on)."""
        self.counters["bad_files"] = self.counters.get("bad_files", 0) + 1
        msg = str(exc) if isinstance(exc, formats.FormatError) else f"{f}: {type(exc).__name__}: {exc}"
        if f not in msg:
            msg = f"{f}: {msg}"
        if len(self.bad_reasons) < 20:
            self.bad_reasons.append(msg)
        if self.counters["files"]:
            log.warning("%s: skipped a file that cannot be read: %s", self.source_id, msg)
        else:  # said once a file was read; if none can be, the stage's error says them (once)
            self._unsaid.append(msg)

    def _read_one(self) -> None:
        """A file was read: count it, and say the files skipped before it."""
        self.counters["files"] += 1
        for msg in self._unsaid:
            log.warning("%s: skipped a file that cannot be read: %s", self.source_id, msg)
        self._unsaid.clear()

    def _progress(self, done: int, total: int | None) -> None:
        """Counters for the progress line; once, a line when the ring starts to overrun."""
        if total and self.o.progress != "off":
            self.counters["total"] = total
            self.counters["progress"] = done / total
        cap = self.ring_capacity
        if cap is None or self._overrun_said or done <= cap:
            return
        self._overrun_said = True
        if self.mode == "stream" and not self.counters["loops"]:
            of = f"of its {total:,} points " if total else ""
            log.warning("%s: %s has sent %s points, more than the ring holds (ring.max_points %s): from here on "
                        "the ring keeps at most %s of them (ring.eviction decides which; the rest count as "
                        "ring_evicted), so %sonly the last %s stay in view. To keep a big static file whole, "
                        "raise ring.max_points (memory permitting), or show it as a map: a `map: {path: %s}` "
                        "block (COPC, LAS/LAZ, PLY, PCD) serves a big static file by level of detail, beside a live "
                        "source (docs/map.md)",
                        self.source_id, os.path.basename(self.files[0]),
                        f"{done:,}", f"{cap:,}", f"{cap:,}", of, f"{cap:,}", os.path.basename(self.files[0]))
        else:  # a replay of scans (or a loop) rolls through the ring as a live sensor does
            log.info("%s: the replay has sent %s points, more than the ring holds (%s): older points are "
                     "evicted from now on, as from a live sensor", self.source_id, f"{done:,}", f"{cap:,}")

    def chunks(self) -> Iterator[Optional[PointChunk]]:
        """Messages (a scan file in ``scans`` mode, a chunk of ``chunk_points`` in ``stream``
        mode) paced by :attr:`playback`, which also pauses, seeks, steps and loops them."""
        o, clock = self.o, self.playback
        if self.mode == "scans":
            clock.duration_s, clock.messages = len(self.files) / o.rate, len(self.files)
        elif self.total is not None:
            clock.duration_s = self.total / o.points_per_second
        start = clock.start_s()
        while True:
            yield from self._pass(start)
            seek = clock.take_seek()
            if seek is not None:
                start = seek
                continue
            if not self.counters["files"]:  # none can be read: an empty replay would look like success
                raise InputUnreadable(f"source {self.source_id!r}: none of its {len(self.files)} file(s) can be read: "
                                      + "; ".join(self.bad_reasons))
            if self.mode == "stream" and clock.duration_s is None and self.total is not None:
                clock.duration_s = self.total / o.points_per_second  # known once a pass has counted it
            if not clock.loop:
                yield from clock.hold_at_end()  # with hold: wait for a seek
                if clock.seek_pending:
                    start = clock.take_seek()
                    continue
            if not clock.loop:
                break
            self.counters["loops"] += 1
            clock.restart(self._pass_s)  # the schedule goes on: one period from the last message to the next pass
            start = 0.0
        if self.mode == "stream" and not clock.seek_pending:  # the last chunk's time has to pass, as live
            yield from clock.pace(self.total / o.points_per_second if self.total else clock.position_s, counts=False)
        self._progress(self.counters["points"], self.total)

    def _pass(self, start_s: float):
        """One pass from the first message at or after ``start_s``; False when a seek cut it short.
        Sets :attr:`_pass_s`, the pass's length in seconds of recording (where the next pass of
        a loop starts): ``files / rate`` for scans, ``points / points_per_second`` for a stream."""
        o, clock = self.o, self.playback
        self._pass_s = len(self.files) / o.rate if self.mode == "scans" else 0.0
        index = 0
        sent_points = 0  # stream mode: points before this chunk in the file
        for i, f in enumerate(self.files):
            if self.mode == "scans":
                t = i / o.rate
                if t < start_s - 1e-9:
                    clock.skipped_messages += 1
                    continue
                yield from clock.pace(t)
                if clock.seek_pending:
                    return False
            try:
                for pos, ch in self._pieces(f):
                    n = pos.shape[0]
                    if self.mode == "stream":
                        t = sent_points / o.points_per_second
                        index += 1
                        sent_points += n
                        if t < start_s - 1e-9:
                            clock.skipped_messages += 1
                            continue
                        yield from clock.pace(t)
                        if clock.seek_pending:
                            return False
                    self.counters["points"] += n
                    total = self.total if self.mode == "stream" else None
                    self._progress(self.counters["points"], total)
                    clock.released(t, i if self.mode == "scans" else index - 1)
                    yield PointChunk(positions=pos, channels=self._channels(ch), source_id=self.source_id)
            except Exception as exc:  # noqa: BLE001 - a bad file is skipped, never the end of the stage
                self._bad_file(f, exc)
                yield None  # the stage beats between files, however many are bad
                continue
            self._read_one()
        if self.mode == "stream":
            clock.messages = index
            self._pass_s = sent_points / o.points_per_second  # the last chunk's points take their time too
        return True
