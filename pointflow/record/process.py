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

With ``frames.fixed`` set, ingest also forwards each transforms message it accepts (the
``pointflow.transforms/1`` JSON, as on the ingest socket) on the same socket; they are
written as ``tf2_msgs/msg/TFMessage`` on ``/tf`` (dynamic, as they arrive) and ``/tf_static``
(every static transform known, ``frames.static`` included: at the start of each file and again
whenever one changes), so viewers show the frame tree and each split file stands alone.
"""
from __future__ import annotations

import errno
import json
import time

import zmq

from .. import wire
from ..chunk import ChunkError
from ..frames import message as transforms
from ..stage.kinds import StageKind, register_stage_kind
from ..stage.context import RateLimitedLog, take_messages
from .encode import Layout, Scratch, encode_pointcloud2, encode_tf, layout_key
from .files import RecordingFiles

#: On stop, take what ingest sent until the socket is quiet this long (at most STOP_GRACE_S).
def wanted(cfg) -> bool:
    """A run records with a ``record:`` block (or ``--record``); its path is checked (and
    its directory made) before anything starts: ConfigError naming ``record.path``."""
    if cfg.record is None:
        return False
    from .config import prepare_record_path

    prepare_record_path(cfg.record)
    return True


#: Binds the socket ingest sends its copies to: starts before ingest; stops last, after it
#: took what ingest sent.
KIND = register_stage_kind(StageKind(
    name="recorder", main="pointflow.record.process:main", start_order=25, stop_wave=2,
    counters=("record_messages", "record_files", "record_bytes", "record_transforms", "rejected_messages"),
    accounting="pointflow.record.accounting:record_identities", wanted="pointflow.record.process:wanted"))

STOP_QUIET_S = 0.2
STOP_GRACE_S = 3.0


class Recorder:
    """Decode, encode and write, with exact counters (no process of its own, so the tests
    and the benchmark can drive it directly)."""

    def __init__(self, rc, counters, log, fresh: bool = True, frames=None):
        self.rc = rc
        self.counters = counters
        self.log = log
        self.files = RecordingFiles(rc, fresh=fresh, log=log)
        self.layouts: dict[tuple, Layout] = {}
        self.scratch = Scratch()
        self.failed: str | None = None
        self.last_log_ns = 0
        self.keep = set(rc.channels) if rc.channels is not None else None
        self._warn = RateLimitedLog(log)
        #: (parent, child) -> the newest static transform (``frames.static`` first)
        self.static: dict[tuple[str, str], transforms.Transform] = {}
        self.transforms_written = 0
        if frames is not None and frames.fixed and frames.static:
            from ..frames.config import static_rotation

            self.add_transforms(transforms.Transforms([
                transforms.Transform(s.parent, s.child, 0, tuple(s.translation), tuple(static_rotation(s)), True)
                for s in frames.static]))
        if not fresh and frames is not None and frames.fixed:
            # a restarted recorder: its new file starts with the statics received before
            try:
                self.add_transforms(transforms.Transforms(recorded_static(self.files.path)))
            except Exception as exc:  # noqa: BLE001 - the recording goes on without them
                log.warning("the static transforms of the earlier file could not be read (%s: %s); "
                            "the new file gets them when they change", type(exc).__name__, exc)

    def add_frames(self, frames) -> None:
        raw = memoryview(getattr(frames[0], "buffer", frames[0])) if len(frames) == 1 else None
        if raw is not None and transforms.SCHEMA_BYTES in bytes(raw[:64]):
            try:
                batch = transforms.decode(json.loads(bytes(raw)))
            except (ValueError, transforms.TransformMessageError) as exc:
                self.counters.extra["rejected_messages"] = self.counters.extra.get("rejected_messages", 0) + 1
                self.log.warning("dropped a malformed transforms message on the record socket: %s", exc)
                return
            self.add_transforms(batch)
            return
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
        now = self._now()
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

    def add_transforms(self, batch: transforms.Transforms) -> None:
        """Dynamic transforms to /tf now; static ones to /tf_static when one is new or changed."""
        if self.failed:
            return
        dynamic = [t for t in batch.transforms if not t.static]
        changed = False
        for t in batch.transforms:
            if t.static and self.static.get((t.parent, t.child)) != t:
                self.static[(t.parent, t.child)] = t
                changed = True
        f = self.files
        try:
            if changed:
                f.static_tf = encode_tf(self.static.values())
                if f.writer is not None and f.file_first_ns:  # else the next file starts with it
                    now = self._now()
                    f.write_tf(True, f.static_tf, now, now)
            if dynamic:
                now = self._now()
                f.write_tf(False, encode_tf(dynamic), now, max(t.stamp_ns for t in dynamic) or now)
                self.transforms_written += len(dynamic)
        except OSError as exc:
            self._fail(exc, 0)

    def _now(self) -> int:
        now = max(time.time_ns(), self.last_log_ns)  # log times never go back within a recording
        self.last_log_ns = now
        return now

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
                "record_messages": f.messages, "record_error": self.failed or "",
                **({"record_transforms": self.transforms_written} if self.transforms_written else {})}


#: A restarted recorder reads at most this far into a file for its last /tf_static.
STATIC_SCAN_BYTES = 64 << 20


def recorded_static(path: str) -> list[transforms.Transform]:
    """The newest /tf_static the recording's files hold (read up to a crash's cut; in a big
    file, the last one in its first ``STATIC_SCAN_BYTES``), so that a restarted recorder's
    file carries the static transforms ingest sent only once."""
    import struct

    from mcap.exceptions import McapError
    from mcap.reader import NonSeekingReader
    from mcap_ros2.decoder import DecoderFactory

    from .files import TF_STATIC_TOPIC, existing_parts

    for _, p in reversed(existing_parts(path)):
        last = None
        try:
            with open(p, "rb") as f:
                for schema, channel, msg in NonSeekingReader(f).iter_messages(log_time_order=False):
                    if channel.topic == TF_STATIC_TOPIC:
                        last = (schema, channel, msg)
                    elif last is not None and f.tell() > STATIC_SCAN_BYTES:
                        break
        except (McapError, OSError, ValueError, EOFError, struct.error):
            pass  # cut short: what was read before counts
        if last is not None:
            schema, channel, msg = last
            m = DecoderFactory().decoder_for(channel.message_encoding, schema)(msg.data)
            return [transforms.Transform(t.header.frame_id, t.child_frame_id,
                                         t.header.stamp.sec * 1_000_000_000 + t.header.stamp.nanosec,
                                         (t.transform.translation.x, t.transform.translation.y,
                                          t.transform.translation.z),
                                         (t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z,
                                          t.transform.rotation.w), True)
                    for t in m.transforms]
    return []


def main(ctx) -> None:
    """Stage loop (:data:`KIND`)."""
    rc = ctx.cfg.record
    sock = ctx.zmq.socket(zmq.PULL)
    sock.setsockopt(zmq.RCVHWM, rc.queue_messages)
    sock.setsockopt(zmq.LINGER, 0)
    sock.bind(ctx.endpoints.record)
    rec = Recorder(rc, ctx.counters, ctx.log, fresh=ctx.info.restart_count == 0, frames=ctx.cfg.frames)
    # counters of files written by earlier incarnations are carried by the supervisor
    ctx.on_beat.append(lambda: ctx.counters.extra.update(rec.stats()))

    try:
        while ctx.running:
            ctx.beat()
            if sock.poll(50, zmq.POLLIN):
                take_messages(sock, rec.add_frames, 16)
            rec.flush()
        ctx.drain_until_quiet(sock, lambda: take_messages(sock, rec.add_frames, 64), STOP_QUIET_S, STOP_GRACE_S)
        rec.close()
    finally:
        ctx.counters.extra.update(rec.stats())
        sock.close()
