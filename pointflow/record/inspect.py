"""``pointflow inspect FILE.mcap``: what a recording holds (topics, message and point counts,
time range) and whether its summary is intact; ``--recover OUT.mcap`` rewrites a file a crash
cut short (no summary) with the ``mcap`` library's writer, so tools that need the summary
(seeking readers, ``ros2 bag info``) open it."""
from __future__ import annotations

import datetime
import os
import struct
import sys
from typing import Any


def _points(data) -> int:
    """width x height of a CDR PointCloud2, read from its first fields (no decoding)."""
    if len(data) < 20:
        return 0
    (slen,) = struct.unpack_from("<I", data, 12)
    off = 16 + slen
    off += (-(off - 4)) % 4  # CDR alignment counts from after the 4-byte encapsulation header
    if off + 8 > len(data):
        return 0
    h, w = struct.unpack_from("<II", data, off)
    return h * w


def scan(path: str) -> dict[str, Any]:
    """Read the whole file record by record (works on files a crash cut short)."""
    from mcap.exceptions import McapError
    from mcap.reader import NonSeekingReader, make_reader

    with open(path, "rb") as f:
        if f.read(8) != b"\x89MCAP0\r\n":
            raise ValueError("not an MCAP file (no MCAP magic at its start)")
    out: dict[str, Any] = {"path": path, "bytes": os.path.getsize(path), "topics": {}, "messages": 0, "points": 0,
                           "start_ns": None, "end_ns": None, "summary_intact": False, "complete": True, "error": ""}
    try:
        with open(path, "rb") as f:
            out["summary_intact"] = make_reader(f).get_summary() is not None
    except (McapError, OSError, ValueError, struct.error, EOFError):
        out["summary_intact"] = False
    topics: dict[str, dict[str, Any]] = out["topics"]
    with open(path, "rb") as f:
        try:
            for schema, channel, msg in NonSeekingReader(f).iter_messages(log_time_order=False):
                t = topics.get(channel.topic)
                if t is None:
                    t = topics[channel.topic] = {"schema": schema.name if schema else "", "messages": 0, "points": 0,
                                                 "source": channel.metadata.get("pointflow.source", "")}
                n = _points(msg.data) if schema is not None and schema.name.endswith("PointCloud2") else 0
                t["messages"] += 1
                t["points"] += n
                out["messages"] += 1
                out["points"] += n
                lt = msg.log_time
                out["start_ns"] = lt if out["start_ns"] is None else min(out["start_ns"], lt)
                out["end_ns"] = lt if out["end_ns"] is None else max(out["end_ns"], lt)
        except (McapError, struct.error, EOFError, ValueError) as exc:
            out["complete"] = False  # cut short (a crash): everything before is read
            out["error"] = f"{type(exc).__name__}: {exc}"
    return out


def _t(ns: int | None) -> str:
    if ns is None:
        return "-"
    return datetime.datetime.fromtimestamp(ns / 1e9, datetime.timezone.utc).isoformat(timespec="milliseconds")


def format_scan(s: dict[str, Any]) -> str:
    lines = [f"{s['path']}: {s['bytes'] / 1e6:.2f} MB, {s['messages']:,} messages, {s['points']:,} points"]
    dur = (s["end_ns"] - s["start_ns"]) / 1e9 if s["start_ns"] is not None else 0.0
    lines.append(f"  time: {_t(s['start_ns'])} .. {_t(s['end_ns'])} ({dur:.3f} s)")
    if s["summary_intact"]:
        lines.append("  summary: intact")
    else:
        lines.append("  summary: MISSING (the writer did not finish, e.g. it was killed); every complete chunk "
                     "was read" + (f" up to the cut ({s['error']})" if s["error"] else "") +
                     "; `pointflow inspect FILE --recover OUT.mcap` writes a copy with a summary")
    for topic, t in sorted(s["topics"].items()):
        src = f"  source {t['source']}" if t["source"] else ""
        lines.append(f"  {topic}  {t['schema']}  {t['messages']:,} messages  {t['points']:,} points{src}")
    return "\n".join(lines)


def recover(path: str, out_path: str) -> dict[str, Any]:
    """Copy every message of a (possibly cut-short) recording into a new, finished file:
    written beside ``out_path`` and renamed over it at the end, so ``out_path`` may even be
    ``path`` itself (the recording is replaced only once its copy is whole)."""
    import tempfile

    fd, tmp = tempfile.mkstemp(prefix=".recover-", suffix=".mcap", dir=os.path.dirname(os.path.abspath(out_path)))
    os.close(fd)
    try:
        r = _recover_into(path, tmp)
        os.replace(tmp, out_path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return {**r, "path": out_path}


def _recover_into(path: str, out_path: str) -> dict[str, Any]:
    from mcap.exceptions import McapError
    from mcap.reader import NonSeekingReader
    from mcap.writer import Writer

    n = 0
    schemas: dict[int, int] = {}
    chans: dict[int, int] = {}
    with open(path, "rb") as f, open(out_path, "wb") as g:
        w = Writer(g)
        w.start(profile="ros2", library="pointflow recover")
        try:
            for schema, channel, msg in NonSeekingReader(f).iter_messages(log_time_order=False):
                if schema is not None and schema.id not in schemas:
                    schemas[schema.id] = w.register_schema(schema.name, schema.encoding, schema.data)
                if channel.id not in chans:
                    chans[channel.id] = w.register_channel(channel.topic, channel.message_encoding,
                                                           schemas.get(channel.schema_id, 0), channel.metadata)
                w.add_message(chans[channel.id], msg.log_time, msg.data, msg.publish_time, msg.sequence)
                n += 1
        except (McapError, struct.error, EOFError, ValueError):
            pass  # the cut: everything before it is copied
        w.finish()
    return {"messages": n, "path": out_path}


def inspect_main(path: str, recover_to: str | None = None) -> int:
    if os.path.isdir(path):
        print(f"error: {path}: a folder; inspect reads one MCAP file (a ROS 2 bag folder: name its .mcap "
              f"file, or replay the folder with a rosbag source)", file=sys.stderr)
        return 1
    if not os.path.isfile(path):
        print(f"error: {path}: no such file", file=sys.stderr)
        return 1
    if recover_to:
        out_dir = os.path.dirname(os.path.abspath(recover_to))
        if os.path.isdir(recover_to) or not os.path.isdir(out_dir):
            print(f"error: --recover {recover_to}: " + ("a folder; name the file to write" if os.path.isdir(recover_to)
                                                         else f"no folder {out_dir} to write it in"), file=sys.stderr)
            return 1
    try:
        s = scan(path)
    except Exception as exc:  # noqa: BLE001 - one line, no traceback: not an MCAP file
        print(f"error: {path}: cannot read as MCAP: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    print(format_scan(s))
    if recover_to:
        try:
            r = recover(path, recover_to)
        except OSError as exc:
            print(f"error: --recover {recover_to}: {exc.strerror or exc}", file=sys.stderr)
            return 1
        print(f"recovered {r['messages']:,} messages into {recover_to} (with a summary)")
    return 0


def record_summary(stats: dict) -> str:
    """One line for the end of ``pointflow run --record``."""
    rec = stats.get("stages", {}).get("recorder", {})
    acc = stats.get("accounting", {})
    files = rec.get("record_files", 0)
    err = rec.get("record_error", "")
    line = (f"recorded {rec.get('points_out', 0):,} points in {rec.get('record_messages', 0):,} messages, "
            f"{rec.get('record_bytes', 0) / 1e6:.1f} MB, to {rec.get('record_file', '') or '-'}"
            + (f" ({files} files)" if files > 1 else "")
            + f"; dropped {acc.get('record_dropped', 0):,} at ingest, {acc.get('recorder_dropped', 0):,} at the recorder")
    if err:
        line += f" (recording stopped: {err})"
    return line
