"""The recording's files: one MCAP writer at a time, split by size or duration, and a new
file (never an overwrite) for every restart of the recorder.

Naming: the first file is ``record.path`` itself (``out/demo.mcap``); every further split or
restart file is ``<stem>.<NNNN>.mcap`` beside it (``out/demo.0001.mcap``). A fresh run
overwrites ``record.path`` and removes the numbered files an earlier run left under the same
name (they would mix with the new ones); a restarted recorder takes the next free number.

Crash safety: the writer's output goes to the file descriptor unbuffered, so every MCAP chunk
the writer completes is in the kernel at once and survives a SIGKILL of this process or of the
whole pipeline; the chunk being filled (at most ``chunk_size`` bytes or ``flush_s`` seconds of
data) and the summary at the end are what such a kill loses. ``pointflow inspect --recover``
(or ``mcap recover``) rewrites such a file with its summary.
"""
from __future__ import annotations

import glob
import os
import re
import time
from typing import Any, Optional

from .config import RecordConfig, topic_for
from .encode import SCHEMA_NAME, SCHEMA_TEXT, TF_SCHEMA_NAME, TF_SCHEMA_TEXT

PROFILE = "ros2"
#: The transform topics (docs/record.md), named as ROS 2 names them whatever ``record.topic`` is.
TF_TOPIC, TF_STATIC_TOPIC = "/tf", "/tf_static"
#: ``ros2 bag``'s channel metadata for /tf_static: reliable, transient local (latched), so
#: ``ros2 bag play`` republishes it the way tf2's static broadcaster does.
STATIC_QOS = """\
- history: 3
  depth: 0
  reliability: 1
  durability: 1
  deadline:
    sec: 2147483647
    nsec: 4294967295
  lifespan:
    sec: 2147483647
    nsec: 4294967295
  liveliness: 1
  liveliness_lease_duration:
    sec: 2147483647
    nsec: 4294967295
  avoid_ros_namespace_conventions: false
"""


class RawOut:
    """The minimal stream the ``mcap`` writer needs, writing straight to a descriptor (no
    Python buffer that a SIGKILL would lose)."""

    def __init__(self, path: str, fresh: bool):
        flags = os.O_WRONLY | os.O_CREAT | os.O_CLOEXEC | (os.O_TRUNC if fresh else os.O_EXCL)
        self.fd = os.open(path, flags, 0o644)
        self.pos = 0

    def write(self, data: Any) -> int:
        mv = memoryview(data).cast("B")
        total = len(mv)
        while mv:
            k = os.write(self.fd, mv)
            mv = mv[k:]
        self.pos += total
        return total

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        pass

    def close(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1


def part_path(path: str, index: int) -> str:
    if index == 0:
        return path
    root, ext = os.path.splitext(path)
    return f"{root}.{index:04d}{ext or '.mcap'}"


def existing_parts(path: str) -> list[tuple[int, str]]:
    """(index, path) of the recording's files on disk, in order."""
    root, ext = os.path.splitext(path)
    ext = ext or ".mcap"
    pat = re.compile(re.escape(os.path.basename(root)) + r"\.(\d{4,})" + re.escape(ext) + "$")
    out = [(0, path)] if os.path.exists(path) else []
    for p in glob.glob(glob.escape(root) + ".*" + ext):
        m = pat.match(os.path.basename(p))
        if m:
            out.append((int(m.group(1)), p))
    return sorted(out)


class RecordingFiles:
    """Writes messages to the current file and rotates (see the module docstring)."""

    def __init__(self, rc: RecordConfig, fresh: bool, log):
        from mcap.writer import CompressionType

        self.rc = rc
        self.path = os.path.abspath(rc.path)
        self.log = log
        self.compression = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                            "none": CompressionType.NONE}[rc.compression]
        if fresh:
            stale = [p for i, p in existing_parts(self.path) if i > 0]
            for p in stale:
                os.unlink(p)
            if stale:
                log.warning("removed %d numbered file(s) of an earlier recording to %s: %s", len(stale),
                            rc.path, ", ".join(os.path.basename(p) for p in stale))
            self.next_index = 0
        else:  # a restarted recorder: the next free number, never an overwrite
            have = existing_parts(self.path)
            self.next_index = (have[-1][0] + 1) if have else 0
        self.fresh = fresh
        self.writer = None
        self.out: Optional[RawOut] = None
        self.current: Optional[str] = None
        self.files: list[str] = []
        self.channels: dict[str, int] = {}
        self.schema_id = 0
        self.tf_schema_id = 0
        #: The encoded TFMessage of every static transform known (set by the recorder): written
        #: to /tf_static first in every file, so each split or restart file is self-contained.
        self.static_tf: Optional[bytes] = None
        self.file_first_ns = 0
        self.bytes_done = 0  # bytes of closed files
        self.messages = 0
        self.file_messages = 0
        self.last_flush = time.monotonic()

    # ------------------------------------------------------------------ files
    def _open(self) -> None:
        from mcap.writer import Writer

        path = part_path(self.path, self.next_index)
        self.out = RawOut(path, fresh=self.fresh and self.next_index == 0)
        self.next_index += 1
        self.current = path
        self.files.append(path)
        self.writer = Writer(self.out, chunk_size=self.rc.chunk_size, compression=self.compression)
        self.writer.start(profile=PROFILE, library="pointflow")
        self.schema_id = self.writer.register_schema(SCHEMA_NAME, "ros2msg", SCHEMA_TEXT.encode())
        self.channels = {}
        self.tf_schema_id = 0
        self.file_first_ns = 0
        self.file_messages = 0
        self.log.info("recording to %s", path)

    def _close(self) -> None:
        if self.writer is None:
            return
        try:
            self.writer.finish()
        finally:
            self.bytes_done += self.out.pos
            self.out.close()
            self.writer = None

    def abandon(self) -> None:
        """After a write error: close the descriptor without writing anything more."""
        if self.out is not None:
            self.bytes_done += self.out.pos
            try:
                self.out.close()
            except OSError:
                pass
        self.writer = None

    # ------------------------------------------------------------------ write
    def write(self, source_id: str, data, log_ns: int, publish_ns: int, seq: int) -> None:
        self._begin(log_ns)
        topic = topic_for(self.rc.topic, source_id)
        cid = self.channels.get(topic)
        if cid is None:
            cid = self.channels[topic] = self.writer.register_channel(
                topic, "cdr", self.schema_id, {"pointflow.source": source_id})
        self._add(cid, log_ns, data, publish_ns, seq)

    def write_tf(self, static: bool, data: bytes, log_ns: int, publish_ns: int) -> None:
        """One TFMessage on /tf (or /tf_static)."""
        self._begin(log_ns)
        self._add(self._tf_channel(static), log_ns, data, publish_ns, 0)

    def _tf_channel(self, static: bool) -> int:
        topic = TF_STATIC_TOPIC if static else TF_TOPIC
        cid = self.channels.get(topic)
        if cid is None:
            if not self.tf_schema_id:
                self.tf_schema_id = self.writer.register_schema(TF_SCHEMA_NAME, "ros2msg", TF_SCHEMA_TEXT.encode())
            meta = {"offered_qos_profiles": STATIC_QOS} if static else {}
            cid = self.channels[topic] = self.writer.register_channel(topic, "cdr", self.tf_schema_id, meta)
        return cid

    def _begin(self, log_ns: int) -> None:
        """Open a file when none is open; a new file starts with the static transforms."""
        if self.writer is None:
            self._open()
        if not self.file_first_ns:
            self.file_first_ns = log_ns
            if self.static_tf is not None:
                self.writer.add_message(self._tf_channel(True), log_ns, self.static_tf, log_ns, 0)
                self.messages += 1
                self.file_messages += 1

    def _add(self, cid: int, log_ns: int, data, publish_ns: int, seq: int) -> None:
        self.writer.add_message(cid, log_ns, data, publish_ns, seq & 0xFFFFFFFF)
        self.messages += 1
        self.file_messages += 1
        sp = self.rc.split
        if (sp.size_mb and self.out.pos >= sp.size_mb * 1e6) or \
                (sp.duration_s and log_ns - self.file_first_ns >= sp.duration_s * 1e9):
            self._close()  # the next message opens the next file

    def maybe_flush(self) -> None:
        """Close the chunk being filled when it is older than ``flush_s``."""
        now = time.monotonic()
        if now - self.last_flush >= self.rc.flush_s:
            self.last_flush = now
            if self.writer is not None:
                self.writer.flush()

    def close(self) -> None:
        self._close()

    @property
    def bytes_written(self) -> int:
        return self.bytes_done + (self.out.pos if self.writer is not None and self.out is not None else 0)
