"""The recorder stage: chunks from ingest (ZeroMQ PULL on ``endpoints.record``) into MCAP.

Ingest hands every chunk it pushes into the ring to this stage as well, over a PUSH socket
with a small high-water mark and without ever waiting: when this stage (or its disk) is
slower than the stream, ingest drops its copy for the recording and counts it
(``record_dropped``); the pipeline never slows down for the recording. Each chunk becomes
one ``sensor_msgs/msg/PointCloud2`` message (:mod:`.encode`) on its source's topic, with
``log_time`` = when this stage received it and ``header.stamp`` (and ``publish_time``) = the
chunk's capture time, or ingest's wall-clock time when the source has none.

A write error (disk full, file system gone) is logged once as one line; the stage stays up,
takes the chunks and counts them as dropped (``drops[disk_full]`` or ``drops[write_error]``),
so the pipeline runs on without the recording. A chunk that cannot be encoded is counted as
``drops[encode_error]`` (logged, rate-limited) and the recording goes on. Accounting::

    points_in (received from ingest) = points_out (written) + sum(drops)
"""
from __future__ import annotations

import errno
import time

import zmq

from .. import wire
from ..chunk import ChunkError
from .encode import Layout, Scratch, encode_pointcloud2, layout_key
from .files import RecordingFiles

#: On stop, take what ingest sent until the socket is quiet this long (at most STOP_GRACE_S).
STOP_QUIET_S = 0.2
STOP_GRACE_S = 3.0


class Recorder:
    """Decode, encode and write, with exact counters (no process of its own, so the tests
    and the benchmark can drive it directly)."""

    def __init__(self, rc, counters, log, fresh: bool = True):
        self.rc = rc
        self.counters = counters
        self.log = log
        self.files = RecordingFiles(rc, fresh=fresh, log=log)
        self.layouts: dict[tuple, Layout] = {}
        self.scratch = Scratch()
        self.failed: str | None = None
        self.last_log_ns = 0
        self.keep = set(rc.channels) if rc.channels is not None else None
        from ..ingest.process import RateLimitedLog

        self._warn = RateLimitedLog(log)

    def add_frames(self, frames) -> None:
        try:
            chunk = wire.decode(frames)
        except ChunkError as exc:  # not from our ingest: count it, go on
            self.counters.extra["rejected_messages"] = self.counters.extra.get("rejected_messages", 0) + 1
            self.log.warning("dropped a malformed message on the record socket: %s", exc)
            return
        self.add(chunk)

    def add(self, chunk) -> None:
        n = chunk.n
        self.counters.points_in += n
        if self.failed:
            self.counters.drop(self.failed, n)
            return
        chans = chunk.channels if self.keep is None else {k: v for k, v in chunk.channels.items() if k in self.keep}
        key = layout_key(chunk.positions, chans)
        lay = self.layouts.get(key)
        if lay is None:
            lay = self.layouts[key] = Layout(chunk.positions.dtype, [(k, v.dtype, 1 if v.ndim == 1 else v.shape[1])
                                                                     for k, v in chans.items()])
        now = max(time.time_ns(), self.last_log_ns)  # log times never go back within a recording
        self.last_log_ns = now
        stamp = chunk.stamp_ns or now
        frame_id = getattr(chunk, "frame_id", "") or self.rc.frame_id
        try:
            data = encode_pointcloud2(lay, chunk.positions, chans, stamp, frame_id, self.scratch)
            self.files.write(chunk.source_id, data, now, stamp, chunk.seq)
        except OSError as exc:
            self._fail(exc, n)
            return
        except Exception as exc:  # noqa: BLE001 - one bad chunk must not stop the recording
            self.counters.drop("encode_error", n)
            self._warn("encode_error", f"chunk {chunk.seq} of {chunk.source_id!r} not recorded: "
                                       f"{type(exc).__name__}: {exc}")
            return
        self.counters.points_out += n

    def _fail(self, exc: OSError, n: int) -> None:
        self.failed = "disk_full" if exc.errno in (errno.ENOSPC, errno.EDQUOT) else "write_error"
        self.counters.drop(self.failed, n)
        where = self.files.current or self.rc.path
        self.log.error("recording stopped: cannot write %s: %s; the pipeline goes on without the recording "
                       "(what arrives from now on is counted as drops[%s])", where, exc.strerror or exc, self.failed)
        self.files.abandon()

    def flush(self) -> None:
        if self.failed:
            return
        try:
            self.files.maybe_flush()
        except OSError as exc:
            self._fail(exc, 0)

    def close(self) -> None:
        if self.failed:
            return
        try:
            self.files.close()
        except OSError as exc:
            self._fail(exc, 0)

    def stats(self) -> dict:
        f = self.files
        return {"record_file": f.current or "", "record_files": len(f.files), "record_bytes": f.bytes_written,
                "record_messages": f.messages, "record_error": self.failed or ""}


def main(ctx) -> None:
    """Stage loop (``pointflow.runtime.stage.STAGE_MAINS['recorder']``)."""
    rc = ctx.cfg.record
    sock = ctx.zmq.socket(zmq.PULL)
    sock.setsockopt(zmq.RCVHWM, rc.queue_messages)
    sock.setsockopt(zmq.LINGER, 0)
    sock.bind(ctx.endpoints.record)
    rec = Recorder(rc, ctx.counters, ctx.log, fresh=ctx.info.restart_count == 0)
    # counters of files written by earlier incarnations are carried by the supervisor
    ctx.on_beat.append(lambda: ctx.counters.extra.update(rec.stats()))

    def take(limit: int) -> int:
        got = 0
        for _ in range(limit):
            try:
                frames = sock.recv_multipart(zmq.NOBLOCK, copy=False)
            except zmq.Again:
                break
            rec.add_frames(frames)
            got += 1
        return got

    try:
        while ctx.running:
            ctx.beat()
            if sock.poll(50, zmq.POLLIN):
                take(16)
            rec.flush()
        end = time.monotonic() + STOP_GRACE_S
        while time.monotonic() < end and sock.poll(int(STOP_QUIET_S * 1000), zmq.POLLIN):
            take(64)
            ctx.beat()
        rec.close()
    finally:
        ctx.counters.extra.update(rec.stats())
        sock.close()
