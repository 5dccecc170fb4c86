"""The ``record:`` block (and ``pointflow run --record PATH``): where and how the recorder
stage writes what ingest accepted to MCAP. Only :mod:`pointflow.typed` is imported here, so
``pointflow.config`` can hold a :class:`RecordConfig` without an import cycle."""
from __future__ import annotations

import os
import re
import tempfile
from dataclasses import dataclass, field
from typing import Literal, Optional

from ..stage.endpoints import Endpoint
from ..typed import ConfigError, at_least_one, check, non_negative, positive


#: Ingest -> recorder (only with ``record:``); PULL bound by the recorder.
ENDPOINTS = (Endpoint("record", "record", "ingest -> recorder (PULL bound by the recorder)"),)


@dataclass
class SplitConfig:
    """Start a new file once the current one reaches either limit (0 = no limit)."""

    size_mb: float = field(default=0.0, metadata=check(non_negative))
    duration_s: float = field(default=0.0, metadata=check(non_negative))


@dataclass
class RecordConfig:
    """``record:``: write every chunk ingest hands to the ring to an MCAP file, as ROS 2
    ``sensor_msgs/msg/PointCloud2`` on one topic per source."""

    #: The MCAP file (relative to the working directory). Split and restart files are
    #: ``<stem>.0001.mcap``, ``<stem>.0002.mcap`` ... beside it.
    path: str = "out/recording.mcap"
    #: Topic prefix; a source named ``lidar`` is recorded on ``<topic>/lidar``.
    topic: str = "/pointflow"
    compression: Literal["zstd", "lz4", "none"] = "zstd"
    #: MCAP chunk size in bytes: a chunk is compressed and written when it reaches this;
    #: after a crash the file reads up to its last complete chunk.
    chunk_size: int = field(default=1 << 20, metadata=check(at_least_one))
    #: Also close the current chunk after this many seconds (so a slow stream is on disk).
    flush_s: float = field(default=1.0, metadata=check(positive))
    split: SplitConfig = field(default_factory=SplitConfig)
    #: Channels to record besides x, y, z; null = every channel ingest keeps. Channels named
    #: here are kept by ingest even when rendering does not use them.
    channels: Optional[list[str]] = None
    #: ``header.frame_id`` when a chunk carries none.
    frame_id: str = "map"
    #: Messages ingest may queue for the recorder (ZeroMQ high-water mark); beyond it ingest
    #: drops its copy for the recording (``record_dropped``) and never waits.
    queue_messages: int = field(default=64, metadata=check(at_least_one))


_TOPIC_BAD = re.compile(r"[^A-Za-z0-9_/]+")


def topic_for(prefix: str, source_id: str) -> str:
    """A valid ROS 2 topic name for a source: ``/pointflow/lidar``; ``rosbag:/os/points``
    (a replayed topic) gives ``/pointflow/rosbag/os/points``."""
    # a replayed topic's source id is "<source>:<topic>": the colon becomes a level
    name = _TOPIC_BAD.sub("_", (source_id or "source").replace(":", "/"))
    name = re.sub(r"/+", "/", name).strip("_/") or "source"
    if name[0].isdigit():
        name = "_" + name
    base = "/" + prefix.strip("/") if prefix.strip("/") else ""
    return f"{base}/{name}"


def check_record(rc: RecordConfig, path: str) -> None:
    """Load-time checks (no file-system side effects)."""
    if not rc.path:
        raise ConfigError(f"{path}.path", "must name an .mcap file")
    if _TOPIC_BAD.search(rc.topic) or not rc.topic.startswith("/"):
        raise ConfigError(f"{path}.topic", f"must be a ROS topic prefix like /pointflow, got {rc.topic!r}")
    if rc.channels is not None:
        for i, c in enumerate(rc.channels):
            if c in ("x", "y", "z"):
                raise ConfigError(f"{path}.channels[{i}]", "x, y, z are always recorded; list only channels")


def prepare_record_path(rc: RecordConfig) -> str:
    """Make the recording's folder and check it can be written, before anything starts:
    an unwritable path is a one-line error naming ``record.path``."""
    p = os.path.abspath(rc.path)
    d = os.path.dirname(p)
    if os.path.isdir(p):
        raise ConfigError("record.path", f"{rc.path} is a directory; name an .mcap file")
    up = d
    while up and not os.path.exists(up):
        up = os.path.dirname(up) if os.path.dirname(up) != up else ""
    if up and not os.path.isdir(up):
        raise ConfigError("record.path", f"cannot write {rc.path}: {up} is a file, not a folder")
    try:
        os.makedirs(d, exist_ok=True)
    except OSError as exc:
        raise ConfigError("record.path", f"cannot create the folder of {rc.path}: {exc.strerror or exc}") from None
    try:  # a real write: access() says yes to root even on a read-only file system
        with tempfile.NamedTemporaryFile(dir=d, prefix=".pointflow-probe-"):
            pass
        if os.path.exists(p):
            with open(p, "ab"):
                pass
    except OSError as exc:
        raise ConfigError("record.path", f"cannot write {rc.path}: {exc.strerror or exc}") from None
    return p


def with_record_path(cfg, path: str):
    """The config with recording to ``path`` (``--record``): the ``record:`` block's other
    settings kept, or the defaults."""
    import dataclasses

    rc = dataclasses.replace(cfg.record, path=path) if cfg.record is not None else RecordConfig(path=path)
    check_record(rc, "record")
    return dataclasses.replace(cfg, record=rc)
