"""``rosbag``: replay ``sensor_msgs/PointCloud2`` topics from ROS recordings, no ROS needed.

Reads ROS 1 ``.bag`` files (a glob reads split bags together), ROS 2 bag folders (sqlite3 or MCAP storage, the folder with
``metadata.yaml``) and bare ``.mcap`` / ``.db3`` files through the pure-Python ``rosbags``
package (``pip install 'pointflow[ros]'``). Each message becomes one chunk, decoded by
:mod:`pointflow.ingest.pointcloud2` and stamped with its ``header.stamp``
(``PointChunk.stamp_ns``) and ``header.frame_id``; each topic is its own source id
(``<source>:<topic>``). ``/tf`` and ``/tf_static`` (``tf2_msgs/TFMessage``) of the same
recording are replayed in recorded order with the clouds, for the frames step (docs/frames.md).

Timing: messages are released at their recorded (bag) times divided by ``rate`` (2 = twice
as fast); ``rate: 0`` sends as fast as ingest accepts. Like the file transport a replay is
lossless (the source waits for ingest instead of dropping). ``start``/``end`` cut a window
(seconds from the start of the recording), ``loop`` replays forever. A topic that is not in
the recording, or not a PointCloud2, is a configuration error listing the PointCloud2
topics the recording has and their message counts. A message that cannot be decoded is
rejected (counted as ``rejected_<reason>``) and the replay goes on.
"""
from __future__ import annotations

import dataclasses
import glob
import os
import time
from pathlib import Path
from typing import Any, Iterator, Literal, Optional

from ...chunk import ChunkError, PointChunk
from ...frames.message import Transforms
from ...typed import ConfigError
from ..pointcloud2 import MSGTYPES, PointCloud2Decoder
from ..rostf import TF_MSGTYPES, decode_tf
from ..playback import PlaybackClock
from .base import Transport


@dataclasses.dataclass
class RosbagOptions:
    #: A ROS 1 .bag, a ROS 2 bag folder (metadata.yaml + .db3/.mcap), or a bare .mcap/.db3 file;
    #: a glob (run_*.bag, or demo*.mcap for a split pointflow recording) reads the files together, in time order.
    path: str
    #: PointCloud2 topics to replay; null = every PointCloud2 topic of the recording.
    topics: Optional[list[str]] = None
    #: Speed factor on the recorded timing (1 = as recorded, 2 = twice as fast); 0 = as fast as possible.
    rate: float = 1.0
    #: Replay forever.
    loop: bool = False
    #: Window to replay, seconds from the start of the recording (end: null = to the end).
    start: float = 0.0
    end: Optional[float] = None
    #: Field renames, e.g. {reflectivity: intensity}.
    rename: dict[str, str] = dataclasses.field(default_factory=dict)
    #: Keep only these channels (after renaming); null = every field.
    channels: Optional[list[str]] = None
    #: The share replayed, on the progress line of ``pointflow run``; off: not shown. auto = on.
    progress: Literal["auto", "on", "off"] = "auto"
    #: tf2_msgs/TFMessage topics replayed with the clouds, in recorded order, for the frames
    #: step (docs/frames.md); topics the recording lacks are skipped; [] = none. A topic whose
    #: name ends in ``_static`` is static (ROS 1's latched /tf_static is read whatever the window).
    tf_topics: list[str] = dataclasses.field(default_factory=lambda: ["/tf", "/tf_static"])


def _anyreader():
    try:
        from rosbags.highlevel import AnyReader
    except ImportError:
        raise ConfigError("", "the rosbag transport needs the 'rosbags' package: pip install 'pointflow[ros]'") from None
    return AnyReader


def _expand(path: str) -> list[str]:
    """The recording's paths: a glob gives several (split ROS 1 bags), sorted."""
    if any(c in path for c in "*?[") and not os.path.exists(path):
        return sorted(glob.glob(path))
    return [path]


def _open_reader(path: str):
    """An opened rosbags AnyReader, or ValueError with a message naming the file."""
    AnyReader = _anyreader()
    from rosbags.typesys import Stores, get_typestore

    p = [Path(x) for x in _expand(path)]
    try:
        # ROS 2 bags up to Humble carry no message definitions: PointCloud2 has not changed
        # since, so the latest standard types decode them
        r = AnyReader(p, default_typestore=get_typestore(Stores.LATEST))
        r.open()
    except FileNotFoundError as exc:
        raise ValueError(f"{path}: not a ROS recording ({exc})") from None
    except Exception as exc:  # noqa: BLE001 - rosbags raises its own error types (and struct/sqlite errors)
        hint = ""
        if any(str(x).lower().endswith(".mcap") for x in p):  # cut short (a crash, a copy): its messages are there
            hint = (f"; if the recording was cut short, `pointflow inspect {path} --recover OUT.mcap` "
                    "writes a copy that replays")
        raise ValueError(f"{path}: cannot read as a ROS 1/ROS 2 bag or MCAP file: {type(exc).__name__}: {exc}{hint}") from None
    return r


def pointcloud2_topics(reader) -> dict[str, int]:
    """PointCloud2 topic -> message count."""
    out: dict[str, int] = {}
    for c in reader.connections:
        if c.msgtype in MSGTYPES:
            out[c.topic] = out.get(c.topic, 0) + int(c.msgcount)
    return out


def _describe(topics: dict[str, int]) -> str:
    if not topics:
        return "the recording has no PointCloud2 topics"
    return "PointCloud2 topics in the recording: " + ", ".join(f"{t} ({n} messages)" for t, n in sorted(topics.items()))


class RosbagTransport(Transport):
    name = "rosbag"
    options_schema = RosbagOptions
    lossless = True
    seekable = True

    @classmethod
    def check_options(cls, o: RosbagOptions, path: str, base_dir: str) -> None:
        p = o.path if os.path.isabs(o.path) else os.path.join(base_dir, o.path)
        files = _expand(p)
        if not files or not all(os.path.exists(f) for f in files):
            raise ConfigError(f"{path}.path", f"no such file or folder: {o.path!r} (resolved to {p!r})")
        if len(files) > 1 and not (all(f.endswith(".bag") for f in files) or all(f.endswith(".mcap") for f in files)):
            raise ConfigError(f"{path}.path", f"{o.path!r} matches {len(files)} paths; only split ROS 1 .bag files "
                              f"or bare .mcap files (a split pointflow recording) can be read together "
                              f"(a ROS 2 bag is one folder): {', '.join(files[:5])}")
        if o.rate < 0:
            raise ConfigError(f"{path}.rate", f"must be >= 0 (0 = as fast as possible), got {o.rate!r}")
        if o.start < 0:
            raise ConfigError(f"{path}.start", f"must be >= 0 seconds, got {o.start!r}")
        if o.end is not None and o.end <= o.start:
            raise ConfigError(f"{path}.end", f"must be after start ({o.start} s), got {o.end!r}")
        try:
            _anyreader()
        except ConfigError as exc:
            raise ConfigError(f"{path}.path", str(exc)) from None
        try:
            reader = _open_reader(p)
        except ValueError as exc:
            raise ConfigError(f"{path}.path", str(exc)) from None
        try:  # opening reads only the index/metadata: cheap enough to check topics at load
            have = pointcloud2_topics(reader)
            types = {c.topic: c.msgtype for c in reader.connections}
            duration = (reader.end_time - reader.start_time) / 1e9 if reader.message_count else 0.0
        finally:
            reader.close()
        if o.topics is not None:
            if not o.topics:
                raise ConfigError(f"{path}.topics", f"is empty; {_describe(have)}")
            for i, t in enumerate(o.topics):
                if t not in types:
                    raise ConfigError(f"{path}.topics[{i}]", f"topic {t!r} is not in the recording; {_describe(have)}")
                if t not in have:
                    raise ConfigError(f"{path}.topics[{i}]", f"topic {t!r} is a {types[t]}, not a PointCloud2; {_describe(have)}")
        elif not have:
            others = ", ".join(f"{t} ({ty})" for t, ty in sorted(types.items())) or "none"
            raise ConfigError(f"{path}.path", f"{o.path}: the recording has no PointCloud2 topics (topics: {others})")
        if o.start >= duration and duration > 0:
            raise ConfigError(f"{path}.start", f"{o.start} s is past the end of the recording ({duration:.3f} s long)")
        o.path = os.path.abspath(p)  # the source process may run elsewhere (cwd)

    def __init__(self, options: dict[str, Any], source_id: str):
        super().__init__(options, source_id)
        self.o = RosbagOptions(**options)
        self.decoder = PointCloud2Decoder(self.o.rename, self.o.channels)
        self.counters = {"messages": 0, "points": 0, "loops": 0, "rejected": 0, "deserialize_s": 0.0, "decode_s": 0.0}
        self.reader = None
        #: Pacing (``rate``; 0 = as fast as ingest takes), pause, seek, step, loop.
        self.playback = PlaybackClock(rate=self.o.rate if self.o.rate > 0 else 1.0, loop=self.o.loop,
                                      realtime=self.o.rate > 0)

    def open(self) -> None:
        try:
            self.reader = _open_reader(self.o.path)
        except ConfigError as exc:
            raise RuntimeError(str(exc)) from None
        have = pointcloud2_topics(self.reader)
        wanted = self.o.topics if self.o.topics is not None else sorted(have)
        missing = [t for t in wanted if t not in have]
        if missing or not wanted:
            raise RuntimeError(f"rosbag transport: {self.o.path}: topic(s) {', '.join(missing) or '(none)'} "
                               f"not PointCloud2 topics of the recording; {_describe(have)}")
        self.connections = [c for c in self.reader.connections if c.topic in wanted and c.msgtype in MSGTYPES]
        self.tf_connections = [c for c in self.reader.connections
                               if c.topic in self.o.tf_topics and c.msgtype in TF_MSGTYPES]
        self.connections += self.tf_connections
        self.decoder = PointCloud2Decoder(self.o.rename, self.o.channels, always=self.keep_fields)
        self.t0 = self.reader.start_time
        self.start_ns = self.t0 + int(self.o.start * 1e9)
        self.stop_ns = self.t0 + int(self.o.end * 1e9) if self.o.end is not None else None
        end = self.stop_ns if self.stop_ns is not None else self.reader.end_time
        self.span_ns = max(1, min(end, self.reader.end_time) - self.start_ns)
        self.total = sum(have[t] for t in wanted) if self.o.start == 0 and self.o.end is None else None

    def _progress(self, t_ns: int, final: bool = False) -> None:
        """The share of the recording replayed, for the progress line of ``pointflow run``
        (``transport_progress``): drawn there, in one place, not here (issue 31.7)."""
        if self.o.progress != "off":
            self.counters["progress"] = 1.0 if final else min(1.0, max(0.0, (t_ns - self.start_ns) / self.span_ns))

    def _parse(self, item: tuple[Any, bytes]) -> PointChunk:
        conn, raw = item
        t0 = time.perf_counter()
        msg = self.reader.deserialize(raw, conn.msgtype)
        t1 = time.perf_counter()
        try:
            return self.decoder.decode(msg, f"{self.source_id}:{conn.topic}")
        except ChunkError as exc:  # which of the bag's topics it was (stats count by reason only)
            raise ChunkError(exc.reason, f"topic {conn.topic}: {exc.message}") from None
        finally:  # where a replay's time goes (bench/bench_ros.py): rosbags vs the decoder
            self.counters["deserialize_s"] += t1 - t0
            self.counters["decode_s"] += time.perf_counter() - t1

    def _tf(self, item: tuple[Any, bytes]) -> Transforms:
        conn, raw = item
        msg = self.reader.deserialize(raw, conn.msgtype)
        return decode_tf(msg, conn.topic.endswith("_static"), f"{self.source_id}:{conn.topic}")

    def _static_first(self) -> Iterator[Transforms]:
        """Static transforms recorded before the window (ROS 1 latches /tf_static once, at the start)."""
        static = [c for c in self.tf_connections if c.topic.endswith("_static")]
        if not static or self.o.start <= 0:
            return
        for conn, _, raw in self.reader.messages(connections=static, stop=self.start_ns):
            batch = self.accept(self._tf, (conn, raw))
            if batch is not None:
                self.counters["transforms"] = self.counters.get("transforms", 0) + len(batch)
                yield batch

    def chunks(self) -> Iterator[Optional[PointChunk]]:
        """Messages at their recorded times, paced by :attr:`playback` (which also pauses,
        seeks, steps and loops them; times count from the window's start)."""
        clock = self.playback
        clock.duration_s = self.span_ns / 1e9
        clock.messages = self.total
        yield from self._static_first()
        start = clock.start_s()
        while True:
            count, first_t, last_t = yield from self._pass(start)
            seek = clock.take_seek()
            if seek is not None:
                start = seek
                continue
            if not clock.loop:
                yield from clock.hold_at_end()  # with hold: wait for a seek
                if clock.seek_pending:
                    start = clock.take_seek()
                    continue
            if not clock.loop or not count:
                break  # done, or an empty window: nothing to loop over
            self.counters["loops"] += 1
            if count > 1:  # one mean message interval before the recording starts again
                gap = (last_t - first_t) / (count - 1)
                yield from clock.pace((last_t - self.start_ns + gap) / 1e9, counts=False)
            clock.restart()
            start = 0.0
        self._progress(0, final=True)

    def _pass(self, start_s: float):
        """One pass from ``start_s`` (seconds into the window); (clouds, first, last time)."""
        clock = self.playback
        first_t = last_t = None
        count = 0
        begin = self.start_ns + int(round(start_s * 1e9))
        clouds = [c for c in self.connections if c.msgtype in MSGTYPES]
        index = sum(1 for _ in self.reader.messages(connections=clouds, start=self.start_ns, stop=begin)) \
            if begin > self.start_ns else 0
        clock.skipped_messages += index if start_s > 0 else 0
        for conn, t_ns, raw in self.reader.messages(connections=self.connections, start=begin, stop=self.stop_ns):
            t_s = (t_ns - self.start_ns) / 1e9
            is_tf = conn.msgtype in TF_MSGTYPES
            yield from clock.pace(t_s, counts=not is_tf)
            if clock.seek_pending:
                break
            if is_tf:
                batch = self.accept(self._tf, (conn, raw))
                if batch is not None:
                    self.counters["transforms"] = self.counters.get("transforms", 0) + len(batch)
                yield batch
                continue
            first_t = t_ns if first_t is None else first_t
            last_t = t_ns
            count += 1
            self.counters["messages"] += 1
            clock.released(t_s, index)
            index += 1
            chunk = self.accept(self._parse, (conn, raw))
            self._progress(t_ns)
            if chunk is None:
                yield None
                continue
            if not chunk.stamp_ns:
                chunk.stamp_ns = int(t_ns)  # no header stamp: the recording time
            self.counters["points"] += chunk.n
            yield chunk
        return count, first_t, last_t

    def close(self) -> None:
        if self.reader is not None:
            try:
                self.reader.close()
            except Exception:  # noqa: BLE001
                pass
            self.reader = None
