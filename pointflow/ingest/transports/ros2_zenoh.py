"""``ros2_zenoh``: a live ``sensor_msgs/PointCloud2`` topic from ROS 2 nodes that use
``rmw_zenoh`` (``RMW_IMPLEMENTATION=rmw_zenoh_cpp``), with nothing of ROS installed.

It joins the robot's Zenoh network as one more session (by default a peer connected to the
router at ``tcp/127.0.0.1:7447``, as every rmw_zenoh session is) and speaks rmw_zenoh's
conventions (:mod:`pointflow.ingest.rmw_zenoh`):

* **Discovery**: it reads the ROS graph from the liveliness tokens under
  ``@ros2_lv/<domain_id>/**``. A topic that no PointCloud2 publisher has, while other
  PointCloud2 topics are published, fails the run with one line listing those topics (and a
  topic of another type says what it is); with no PointCloud2 publisher at all it waits.
* **Its own place in the graph**: a node token (``NN``, node ``node_name``) and, per topic, a
  subscription token (``MS``) exactly as rmw_zenoh declares them, so ``ros2 topic info`` on
  the robot lists it and buffer-aware publishers (rmw_zenoh 0.10.5+/0.12.0+), which send only to
  subscriptions they discovered, send to it. The token carries the type hash the topic's
  publishers use (``RIHS01_...``, or ``TypeHashNotSupported`` for Humble) and, for PointCloud2,
  ``backends:cpu:`` (a CPU-only buffer-aware subscription, served on ``_buf_cpu``).
* **Data**: a subscriber on ``<domain_id>/<topic>/sensor_msgs::msg::dds_::PointCloud2_/*``
  (the ``*`` matches every distribution's hash chunk), where Jazzy/Humble publishers put, and
  one on ``.../*/_buf_cpu``, where buffer-aware publishers (rmw_zenoh 0.10.5+ Lyrical, 0.12.0+
  Rolling) put for subscriptions that, as ours, declare ``backends:cpu:``; each sample's CDR
  payload is read by rosbags and decoded by :mod:`pointflow.ingest.pointcloud2`, stamped with
  ``header.stamp``.
* **Peer mode across hosts**: rmw_zenoh's router does not forward between peers and its nodes
  listen on their host's loopback only, so a peer that reaches a remote router and not one ROS
  entity within ``discovery_timeout_s`` reopens as a client of that router, with one warning.
* **Loss**: each sample's attachment carries the publisher's GID and sequence number; a gap is
  counted as ``lost_in_transit_messages`` (and per publisher,
  ``lost_in_transit_messages:<topic>@<gid>``).
* **Transforms**: with ``frames.fixed`` set it also subscribes to ``tf_topics``
  (``tf2_msgs/TFMessage``; ``/tf_static`` as a transient-local subscription that fetches the
  publishers' cached samples, as rmw_zenoh's do) and yields them in arrival order with the clouds.

Samples arrive on Zenoh's threads and wait in a queue of ``queue_messages`` clouds; when the
source loop is behind, the oldest cloud is dropped and counted (``dropped_queue_full``), never
a transform. Needs ``eclipse-zenoh`` and ``rosbags`` (``pip install 'pointflow[remote,ros]'``).
"""
from __future__ import annotations

import collections
import dataclasses
import logging
import threading
import time
from typing import Any, Iterator, Optional

from ...chunk import ChunkError, PointChunk
from ...frames.message import Transforms
from ...remote.zenoh_options import ZenohOpenError, ZenohOptions, check_zenoh, is_loopback_locator, open_session
from ...typed import ConfigError, at_least_one, check, load_dataclass, non_negative, positive
from .. import rmw_zenoh as rz
from ..pointcloud2 import PointCloud2Decoder
from ..rostf import decode_tf
from .base import InputUnreadable, Transport

log = logging.getLogger("pointflow.transport.ros2_zenoh")

PC2 = "sensor_msgs/msg/PointCloud2"
TFM = "tf2_msgs/msg/TFMessage"
#: Where an rmw_zenoh session looks for its router unless told otherwise.
ROUTER = "tcp/127.0.0.1:7447"


@dataclasses.dataclass
class Ros2ZenohOptions:
    #: The PointCloud2 topic, e.g. /ouster/points.
    topic: str = ""
    #: ROS_DOMAIN_ID of the robot (the first chunk of every key).
    domain_id: int = dataclasses.field(default=0, metadata=check(non_negative))
    #: The Zenoh session (docs/remote.md); default: a peer connected to the router at
    #: tcp/127.0.0.1:7447, as rmw_zenoh sessions are.
    zenoh: ZenohOptions = dataclasses.field(default_factory=ZenohOptions)
    #: Field renames, e.g. {reflectivity: intensity}.
    rename: dict[str, str] = dataclasses.field(default_factory=dict)
    #: Keep only these channels (after renaming); null = every field.
    channels: Optional[list[str]] = None
    #: tf2_msgs/TFMessage topics subscribed to when frames.fixed is set (docs/frames.md);
    #: a topic ending in _static is static (transient local); [] = none.
    tf_topics: list[str] = dataclasses.field(default_factory=lambda: ["/tf", "/tf_static"])
    #: How long to read the ROS graph before checking that the topic is published.
    discovery_timeout_s: float = dataclasses.field(default=3.0, metadata=check(positive))
    #: Clouds waiting between Zenoh's threads and the source loop; beyond, the oldest is dropped.
    queue_messages: int = dataclasses.field(default=4, metadata=check(at_least_one))
    #: Our node's name in the ROS graph (namespace /).
    node_name: str = "pointflow"
    #: Clouds larger than this are rejected (too_large).
    max_points: int = dataclasses.field(default=5_000_000, metadata=check(at_least_one))
    #: Stop after this many clouds (0 = never); for tests and captures.
    max_chunks: int = dataclasses.field(default=0, metadata=check(non_negative))


def _topic_ok(t: str) -> bool:
    return t.startswith("/") and len(t) > 1 and "//" not in t and not any(c in t for c in "*$#?% ")


class Ros2ZenohTransport(Transport):
    name = "ros2_zenoh"
    options_schema = Ros2ZenohOptions

    @classmethod
    def check_options(cls, o: Ros2ZenohOptions, path: str, base_dir: str) -> None:
        if not _topic_ok(o.topic):
            raise ConfigError(f"{path}.topic", f"a ROS topic name starting with '/' is required, got {o.topic!r}")
        for i, t in enumerate(o.tf_topics):
            if not _topic_ok(t):
                raise ConfigError(f"{path}.tf_topics[{i}]", f"a ROS topic name starting with '/' is required, got {t!r}")
        if not o.node_name or not o.node_name.replace("_", "a").isalnum():
            raise ConfigError(f"{path}.node_name", f"a ROS node name (letters, digits, _) is required, got {o.node_name!r}")
        check_zenoh(o.zenoh, f"{path}.zenoh", base_dir, connect_default=(ROUTER,))
        for mod, extra in (("zenoh", "remote"), ("rosbags", "ros")):
            try:
                __import__(mod)
            except ImportError:
                raise ConfigError(path, f"the ros2_zenoh transport needs the {mod!r} package: "
                                  f"pip install 'pointflow[{extra}]'") from None

    def __init__(self, options: dict[str, Any], source_id: str):
        super().__init__(options, source_id)
        self.o: Ros2ZenohOptions = load_dataclass(Ros2ZenohOptions, options, "options")
        self.decoder = PointCloud2Decoder(self.o.rename, self.o.channels)
        self.counters = {"messages": 0, "points": 0, "rejected": 0, "transforms": 0, "dropped_queue_full": 0,
                         "deserialize_s": 0.0, "decode_s": 0.0}
        self.ledger = rz.SequenceLedger()
        self._lock = threading.Condition()
        self._queue: collections.deque = collections.deque()
        self._clouds_queued = 0
        self._graph: dict[str, rz.Entity] = {}
        self._graph_changed = False
        self._session = None
        self._undeclare: list[Any] = []          # subscribers and tokens, undeclared on close
        self._sub_tokens: dict[tuple[str, str], Any] = {}   # (topic, type hash) -> our MS token
        self._topic_types = {self.o.topic: PC2}
        self._next_entity = 1
        self._typestore = None
        self._waiting_logged = False
        self._mode = self.o.zenoh.mode

    # ------------------------------------------------------------------ graph
    def _on_token(self, sample) -> None:
        import zenoh

        key = str(sample.key_expr)
        with self._lock:
            if sample.kind == zenoh.SampleKind.DELETE:
                self._graph.pop(key, None)
            else:
                ent = rz.parse_token(key)
                if ent is not None:
                    self._graph[key] = ent
            self._graph_changed = True
            self._lock.notify_all()

    def publishers(self) -> list[rz.Entity]:
        with self._lock:
            return [e for e in self._graph.values() if e.kind == "MP" and e.domain_id == self.o.domain_id]

    def _describe_pc2(self, pubs: list[rz.Entity]) -> str:
        topics: dict[str, int] = {}
        for e in pubs:
            if e.type == PC2:
                topics[e.topic] = topics.get(e.topic, 0) + 1
        if not topics:
            return f"no PointCloud2 topic is published on domain {self.o.domain_id}"
        return (f"PointCloud2 topics published on domain {self.o.domain_id}: "
                + ", ".join(f"{t} ({n} publisher{'s' * (n > 1)})" for t, n in sorted(topics.items())))

    def _check_topic(self, final: bool) -> bool:
        """True once the topic has a PointCloud2 publisher; raises InputUnreadable for a wrong
        topic (when ``final``: after discovery_timeout_s)."""
        pubs = self.publishers()
        mine = [e for e in pubs if e.topic == self.o.topic]
        if any(e.type == PC2 for e in mine):
            return True
        if not final:
            return False
        if mine:
            raise InputUnreadable(f"ros2_zenoh: topic {self.o.topic!r} is a {mine[0].type}, not a "
                                  f"sensor_msgs/msg/PointCloud2; {self._describe_pc2(pubs)}")
        if any(e.type == PC2 for e in pubs):
            raise InputUnreadable(f"ros2_zenoh: topic {self.o.topic!r} has no publisher; {self._describe_pc2(pubs)}")
        return False

    # ------------------------------------------------------------------ our entities
    @staticmethod
    def _buffer_aware(topic: str, typ: str) -> bool:
        """A subscription rmw_zenoh would make buffer-aware: a buffer type, not transient local."""
        return typ in rz.BUFFER_TYPES and not topic.endswith("_static")

    def _cpu_stride(self, topic: str) -> int:
        """Sequence numbers a buffer-aware publisher uses per message while it serves us on
        ``_buf_cpu``: one for that put, one per other (non-CPU-only) subscription of the topic.
        Called with the lock held."""
        typ = self._topic_types.get(topic)
        others = sum(1 for e in self._graph.values()
                     if e.kind == "MS" and e.topic == topic and e.type == typ and not e.cpu_only
                     and e.domain_id == self.o.domain_id)
        return 1 + others

    def _entity(self, kind: str, topic: str = "", typ: str = "", type_hash: str = "", qos: str = "") -> rz.Entity:
        eid = "0" if kind == "NN" else str(self._next_entity)
        if kind != "NN":
            self._next_entity += 1
        return rz.Entity(self.o.domain_id, str(self._session.zid()), "0", eid, kind, "/", "/", self.o.node_name,
                         topic, typ, type_hash, qos)

    def _declare_sub_tokens(self) -> None:
        """One MS token per (topic, type hash) its publishers use, as rmw_zenoh declares for a
        subscription; without a publisher yet, the hash of the type as Iron and later spell it."""
        pubs = self.publishers()
        for topic, typ in self._topic_types.items():
            hashes = {e.type_hash for e in pubs if e.topic == topic and e.type == typ}
            if not hashes and not any(k[0] == topic for k in self._sub_tokens):
                hashes = {self._typestore.hash_rihs01(typ)}
            for h in sorted(hashes - {k[1] for k in self._sub_tokens if k[0] == topic}):
                static = topic.endswith("_static")
                if typ == PC2:
                    qos = rz.qos_chunk(rz.BEST_EFFORT, rz.VOLATILE, 5)
                elif static:
                    qos = rz.qos_chunk(rz.RELIABLE, rz.TRANSIENT_LOCAL, 1)
                else:
                    qos = rz.qos_chunk(rz.RELIABLE, rz.VOLATILE, 100)
                ent = self._entity("MS", topic, typ, h, qos)
                if self._buffer_aware(topic, typ):  # rmw_zenoh 0.10.5+/0.12.0+: serve us on _buf_cpu
                    ent = dataclasses.replace(ent, backends=dict(rz.CPU_ONLY))
                tok = self._session.liveliness().declare_token(ent.key())
                self._sub_tokens[(topic, h)] = tok
                log.debug("%s: declared subscription token %s", self.source_id, ent.key())

    # ------------------------------------------------------------------ samples
    def _on_sample(self, topic: str, sample, cpu_group: bool = False) -> None:
        """On a Zenoh thread: account the sequence number at arrival (so our own queue drops
        are never mistaken for losses on the way), then queue the sample. ``cpu_group``: it
        came on ``<key>/_buf_cpu`` from a buffer-aware publisher."""
        try:
            att: Any = rz.parse_attachment(sample.attachment)
        except rz.AttachmentError as exc:
            att = exc
        payload = sample.payload  # copied out on the source loop's thread, not on Zenoh's
        is_cloud = topic == self.o.topic
        with self._lock:
            if isinstance(att, rz.Attachment):
                self.ledger.observe(topic, att, self._cpu_stride(topic) if cpu_group else 0)
            if cpu_group:
                self.counters["buffer_cpu_messages"] = self.counters.get("buffer_cpu_messages", 0) + 1
            if is_cloud:
                if self._clouds_queued >= self.o.queue_messages:
                    for i, item in enumerate(self._queue):
                        if item[0] == self.o.topic:
                            del self._queue[i]
                            break
                    self._clouds_queued -= 1
                    self.counters["dropped_queue_full"] += 1
                self._clouds_queued += 1
            self._queue.append((topic, payload, att))
            self._lock.notify_all()

    def open(self) -> None:
        from rosbags.typesys import Stores, get_typestore

        self._typestore = get_typestore(Stores.LATEST)
        if self.decoder.always != tuple(self.keep_fields):  # set by the source stage after __init__
            self.decoder = PointCloud2Decoder(self.o.rename, self.o.channels, always=self.keep_fields)
        if self.wants_transforms:
            for t in self.o.tf_topics:
                self._topic_types[t] = TFM
        self._start(self.o.zenoh)
        if self._peer_cut_off():
            routers = ", ".join(self.o.zenoh.connect)
            log.warning("%s: peer mode reached the Zenoh router at %s but no ROS publisher on domain %d: rmw_zenoh's "
                        "router does not forward between peers (peers_failover_brokering: false) and its nodes "
                        "accept connections from their own host only; reopened as a client of the router "
                        "(set zenoh.mode: client to skip this wait, docs/ros.md)",
                        self.source_id, routers, self.o.domain_id)
            self.counters["peer_reopened_as_client"] = 1
            self._stop_session()
            self._start(dataclasses.replace(self.o.zenoh, mode="client", listen=[]))
        found = self._check_topic(final=True)
        self.counters["graph_publishers"] = len(self.publishers())
        self._declare_sub_tokens()
        if found:
            pubs = [e for e in self.publishers() if e.topic == self.o.topic]
            log.info("%s: %s published by %s", self.source_id, self.o.topic,
                     ", ".join(f"{e.namespace.rstrip('/')}/{e.node} ({e.type_hash[:14]})" for e in pubs))
        else:
            self._log_waiting()

    def _start(self, zopts: ZenohOptions) -> None:
        """Open the session, read the graph, declare our node and the data subscribers, and wait
        up to ``discovery_timeout_s`` for the topic's publisher."""
        import zenoh

        try:
            self._session = open_session(zopts)
        except ZenohOpenError as exc:
            raise RuntimeError(str(exc)) from None
        self._mode = zopts.mode
        s = self._session
        deadline = time.monotonic() + self.o.discovery_timeout_s
        if zopts.connect and zopts.mode != "router":
            # the graph is read through the router: give the connection its moment first
            while not list(s.info.routers_zid()) and not list(s.info.peers_zid()) and time.monotonic() < deadline:
                time.sleep(0.02)
        live = s.liveliness()
        self._undeclare.append(live.declare_subscriber(rz.graph_key(self.o.domain_id), self._on_token, history=True))
        self._undeclare.append(live.declare_token(self._entity("NN").key()))
        for topic, typ in self._topic_types.items():
            key = rz.topic_key(self.o.domain_id, topic, typ)
            cb = (lambda t: (lambda sample: self._on_sample(t, sample)))(topic)
            if topic.endswith("_static") and typ == TFM:  # transient local: fetch what publishers cached
                sub = zenoh.ext.declare_advanced_subscriber(
                    s, key, cb, history=zenoh.ext.HistoryConfig(detect_late_publishers=True),
                    subscriber_detection=True)
            else:
                sub = s.declare_subscriber(key, cb)
            self._undeclare.append(sub)
            if self._buffer_aware(topic, typ):
                # buffer-aware publishers (0.10.5+/0.12.0+) serve a CPU-only subscription here, not
                # on the base key, which stays for Jazzy/Humble publishers and mixed graphs
                cpu_cb = (lambda t: (lambda sample: self._on_sample(t, sample, cpu_group=True)))(topic)
                self._undeclare.append(s.declare_subscriber(rz.buffer_cpu_key(key), cpu_cb))
        with self._lock:
            while time.monotonic() < deadline and not self._check_topic(final=False):
                self._lock.wait(min(0.05, max(0.0, deadline - time.monotonic())))

    def _peer_cut_off(self) -> bool:
        """A peer that reached a router on another host, no other peer, and not one publisher:
        rmw_zenohd does not forward between peers and the robot's nodes listen on its loopback
        only. (A robot with no publisher up yet reads the same; a client sees it as well.)"""
        if self._mode != "peer" or all(is_loopback_locator(x) for x in self.o.zenoh.connect):
            return False
        s = self._session
        try:
            if not list(s.info.routers_zid()) or list(s.info.peers_zid()):
                return False
        except Exception:  # noqa: BLE001 - a closed session: nothing to decide
            return False
        me = str(s.zid())
        with self._lock:  # clients' tokens do reach a peer through the router: only publishers tell
            return not any(e.zid != me and e.kind == "MP" for e in self._graph.values()
                           if e.domain_id == self.o.domain_id)

    def _stop_session(self) -> None:
        for obj in list(self._sub_tokens.values()) + self._undeclare[::-1]:
            try:
                obj.undeclare()
            except Exception:  # noqa: BLE001 - the session may already be gone
                pass
        self._sub_tokens.clear()
        self._undeclare.clear()
        if self._session is not None:
            try:
                self._session.close()
            except Exception:  # noqa: BLE001
                pass
            self._session = None
        with self._lock:
            self._graph.clear()

    def _log_waiting(self) -> None:
        if not self._waiting_logged:
            self._waiting_logged = True
            try:
                routers = len(list(self._session.info.routers_zid()))
            except Exception:  # noqa: BLE001 - only for the message
                routers = -1
            self.counters["routers"] = routers
            hint = (f"; no Zenoh router reached at {', '.join(self.o.zenoh.connect) or 'the configured endpoints'} "
                    f"(is `ros2 run rmw_zenoh_cpp rmw_zenohd` running?)" if routers == 0 and self.o.zenoh.mode != "router" else "")
            log.warning("%s: no publisher of %s seen yet on domain %d (%s)%s; waiting for one",
                        self.source_id, self.o.topic, self.o.domain_id, self._describe_pc2(self.publishers()), hint)

    def _parse_cloud(self, payload: bytes) -> PointChunk:
        t0 = time.perf_counter()
        try:
            msg = self._typestore.deserialize_cdr(payload, PC2)
        except Exception as exc:  # noqa: BLE001 - rosbags raises assorted errors on bad CDR
            raise ChunkError("decode_error", f"CDR payload of {len(payload)} bytes: {type(exc).__name__}: {exc}") from None
        t1 = time.perf_counter()
        try:
            return self.decoder.decode(msg, f"{self.source_id}:{self.o.topic}")
        finally:
            self.counters["deserialize_s"] += t1 - t0
            self.counters["decode_s"] += time.perf_counter() - t1

    def _parse_tf(self, item: tuple[str, bytes]) -> Transforms:
        topic, payload = item
        try:
            msg = self._typestore.deserialize_cdr(payload, TFM)
        except Exception as exc:  # noqa: BLE001
            raise ChunkError("decode_error", f"{topic}: CDR payload of {len(payload)} bytes: {type(exc).__name__}: {exc}") from None
        return decode_tf(msg, topic.endswith("_static"), f"{self.source_id}:{topic}")

    def chunks(self) -> Iterator[Optional[PointChunk]]:
        while True:
            with self._lock:
                if not self._queue:
                    self._lock.wait(0.05)
                item = self._queue.popleft() if self._queue else None
                if item is not None and item[0] == self.o.topic:
                    self._clouds_queued -= 1
                changed, self._graph_changed = self._graph_changed, False
            self.counters.update(self.ledger.counters())
            if changed:
                self.counters["graph_publishers"] = len(self.publishers())
                self._declare_sub_tokens()  # a publisher with another type hash: match it too
            if item is None:
                yield None
                continue
            topic, zpayload, att = item
            payload = zpayload.to_bytes()
            if isinstance(att, rz.AttachmentError):  # still decodable: counted, not dropped
                self.counters["no_attachment"] = self.counters.get("no_attachment", 0) + 1
            if topic != self.o.topic:
                batch = self.accept(self._parse_tf, (topic, payload))
                if batch is not None:
                    self.counters["transforms"] += len(batch)
                yield batch
                continue
            self.counters["messages"] += 1
            chunk = self.accept(self._parse_cloud, payload)
            if chunk is not None and chunk.n > self.o.max_points:
                self.reject("too_large", f"{chunk.n} points, more than max_points {self.o.max_points}")
                chunk = None
            if chunk is None:
                yield None
                continue
            if not chunk.stamp_ns and isinstance(att, rz.Attachment):
                chunk.stamp_ns = att.source_timestamp_ns
            self.counters["points"] += chunk.n
            yield chunk
            if self.quota_reached():
                return

    def close(self) -> None:
        self.counters.update(self.ledger.counters())
        self._stop_session()
