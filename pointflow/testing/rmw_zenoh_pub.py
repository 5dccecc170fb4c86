"""A ROS 2 publisher that behaves as rmw_zenoh's does on the wire, for the ``ros2_zenoh`` tests
and benchmarks (there is no ROS 2 here; shipped in the package so bench/ need not import tests/). Written from ros2/rmw_zenoh's released sources with the
``eclipse-zenoh`` package and rosbags' CDR serialiser:

* a node token ``@ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/%/%/<node>`` and, per topic, a publisher
  token ``.../MP/%/%/<node>/<%topic>/<dds type>/<type hash>/<qos>``;
* data on ``<domain>/<topic>/<dds type>/<type hash>``; the hash is ``RIHS01_<hex>`` (computed by
  rosbags, as rosidl does) or ``TypeHashNotSupported`` in ``humble`` mode;
* every sample carries the attachment (int64 sequence number from 1, int64 source time in ns,
  16-byte GID) in Zenoh's serialisation; the GID is XXH3-128 of the publisher's token, as
  rmw_zenoh's ``Entity`` computes it;
* transient-local topics (``/tf_static``) go through an advanced publisher with a cache and
  publisher detection, as rmw_zenoh's do, so a subscription that comes later gets them;
* ``rolling`` (also ``lyrical``) mode is a buffer-aware publisher of rmw_zenoh 0.12.0 (0.10.5 on
  Lyrical), for PointCloud2 topics: its token ends ``backends:cpu:``; it discovers each
  subscription token on the topic (same type) and never forgets one; a subscription whose
  backends are exactly ``cpu`` is served on ``<key>/_buf_cpu`` (one put per message for all of
  them), any other (a token without backends included) on ``<key>/_buf/<its GID hex>``, each put
  numbered; nothing goes on the base key and nothing is sent before a subscription is
  discovered. Its other topics, as ``jazzy``/``humble`` all of theirs, use the base key; those
  modes publish when the test says ``go`` on stdin, ``rolling`` when its topics have a
  subscription (a test convenience for the non-buffer topics).

Run as ``python -m pointflow.testing.rmw_zenoh_pub SPEC.pickle`` (a publisher) or ``python -m
pointflow.testing.rmw_zenoh_pub --router LOCATOR`` (a Zenoh router, as ``rmw_zenohd`` is). It prints ``READY`` once declared,
``MATCHED <token>`` for each subscription token of its topics, ``PATH cpu <token>`` or ``PATH gid
<hex> <token>`` when a buffer-aware topic serves a subscription, ``SENT <topic> <n>`` when a topic's
script is done, and exits when stdin closes.
"""
from __future__ import annotations

import json
import pickle
import sys
import threading
import time

import zenoh
import zenoh.ext

from ..ingest import rmw_zenoh as rz

PC2 = "sensor_msgs/msg/PointCloud2"
_OUT = threading.Lock()


def say(*words) -> None:
    """One whole line (Zenoh calls back on its own threads, beside the main one)."""
    with _OUT:
        sys.stdout.write(" ".join(map(str, words)) + "\n")
        sys.stdout.flush()


TFM = "tf2_msgs/msg/TFMessage"


def _typestore():
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(Stores.LATEST)


def cdr_cloud(cloud) -> bytes:
    """A ros_util.Cloud as rmw_zenoh puts it: encapsulation header + CDR (rosbags)."""
    ts = _typestore()
    return bytes(ts.serialize_cdr(cloud.ros_msg(ts), PC2))


def cdr_tf(items) -> bytes:
    """(parent, child, stamp_ns, translation, quaternion xyzw) items -> TFMessage CDR."""
    ts = _typestore()
    T = ts.types
    out = []
    for parent, child, st, tr, q in items:
        hdr = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=int(st) // 10**9, nanosec=int(st) % 10**9),
                                       frame_id=parent)
        tf = T["geometry_msgs/msg/Transform"](translation=T["geometry_msgs/msg/Vector3"](*map(float, tr)),
                                             rotation=T["geometry_msgs/msg/Quaternion"](*map(float, q)))
        out.append(T["geometry_msgs/msg/TransformStamped"](header=hdr, child_frame_id=child, transform=tf))
    return bytes(ts.serialize_cdr(T[TFM](transforms=out), TFM))


def router(locator: str) -> None:
    """A router configured as rmw_zenohd's DEFAULT_RMW_ZENOH_ROUTER_CONFIG.json5 where it matters
    here: it does not forward between two peers (``peers_failover_brokering: false``)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("routing/router/peers_failover_brokering", "false")
    conf.insert_json5("listen/endpoints", json.dumps([locator]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf):
        say("READY")
        sys.stdin.read()


class Endpoint:
    """One publisher: its token, its Zenoh publishers, its sequence numbers."""

    def __init__(self, session, domain, node, eid, topic, typ, type_hash, reliable=False, buffer_aware=False):
        static = topic.endswith("_static")
        qos = (rz.qos_chunk(rz.RELIABLE, rz.TRANSIENT_LOCAL, 1) if static else
               rz.qos_chunk(rz.RELIABLE if reliable else rz.BEST_EFFORT, rz.VOLATILE, 5))
        self.buffer_aware = buffer_aware and typ in rz.BUFFER_TYPES and not static
        self.entity = rz.Entity(domain, str(session.zid()), "0", str(eid), "MP", "/", "/", node, topic, typ, type_hash,
                                qos, backends=dict(rz.CPU_ONLY) if self.buffer_aware else None)
        self.gid = self.entity.gid()
        self.session = session
        self.key = rz.topic_key(domain, topic, typ, type_hash)
        self.reliable = reliable
        if static:
            self.pub = zenoh.ext.declare_advanced_publisher(
                session, self.key, cache=zenoh.ext.CacheConfig(1), publisher_detection=True,
                reliability=zenoh.Reliability.RELIABLE)
        else:
            self.pub = self._publisher(self.key)
        # buffer-aware: the CPU-group publisher is declared at once, one per subscription GID later
        self.cpu_pub = self._publisher(rz.buffer_cpu_key(self.key)) if self.buffer_aware else None
        self.cpu_subs: list[bytes] = []
        self.gid_pubs: dict[bytes, object] = {}     # subscription GID -> its publisher, in discovery order
        self.lock = threading.Lock()
        self.token = session.liveliness().declare_token(self.entity.key())
        self.seq = 0
        self.seen: set[bytes] = set()               # subscription GIDs seen in the graph
        self.matched = threading.Event()

    def _publisher(self, key: str):
        return self.session.declare_publisher(key, reliability=zenoh.Reliability.RELIABLE if self.reliable
                                              else zenoh.Reliability.BEST_EFFORT,
                                              congestion_control=zenoh.CongestionControl.BLOCK)

    def discover(self, sub: rz.Entity) -> None:
        """A subscription of this topic came into the graph (``on_subscriber_discovered``)."""
        self.seen.add(sub.gid())
        if self.buffer_aware:
            g = sub.gid()
            with self.lock:
                if g in self.cpu_subs or g in self.gid_pubs:
                    return
                if sub.cpu_only:
                    self.cpu_subs.append(g)
                    say("PATH", "cpu", sub.key())
                else:
                    self.gid_pubs[g] = self._publisher(rz.buffer_key(self.key, g))
                    say("PATH", "gid", g.hex(), sub.key())
        self.matched.set()

    def _pubs(self) -> list:
        if not self.buffer_aware:
            return [self.pub]
        with self.lock:
            return ([self.cpu_pub] if self.cpu_subs else []) + list(self.gid_pubs.values())

    def wait_matched(self, timeout: float) -> bool:
        """A subscription is in the graph and Zenoh routes to every publisher this one puts on
        (the token can arrive a moment before the subscriber's declaration)."""
        end = time.monotonic() + timeout
        if not self.matched.wait(timeout):
            return False
        while not all(p.matching_status.matching for p in self._pubs() if hasattr(p, "matching_status")):
            if time.monotonic() > end:
                return False
            time.sleep(0.01)
        return True

    def put(self, payload: bytes) -> None:
        for pub in self._pubs():  # buffer-aware: _buf_cpu once, then each other subscription's key
            self.seq += 1
            pub.put(payload, attachment=rz.encode_attachment(self.seq, time.time_ns(), self.gid))

    def skip(self) -> None:
        """A message lost on the way: its numbers are used, nothing arrives."""
        self.seq += len(self._pubs())


def publish(spec: dict) -> None:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([spec["connect"]]))
    conf.insert_json5("listen/endpoints", json.dumps(["tcp/127.0.0.1:0"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("timestamping/enabled", "true")  # as rmw_zenoh's session config: caches need it
    conf.insert_json5("transport/shared_memory/enabled", "false")  # namespaces share /dev/shm, hosts do not
    mode = spec.get("mode", "jazzy")
    domain = int(spec.get("domain", 0))
    node = spec.get("node", "lidar_driver")
    ts = _typestore()
    session = zenoh.open(conf)
    end = time.monotonic() + 30
    while not list(session.info.routers_zid()) and time.monotonic() < end:  # the graph comes through it
        time.sleep(0.02)
    live = session.liveliness()
    node_tok = live.declare_token(f"{rz.ADMIN_SPACE}/{domain}/{session.zid()}/0/0/NN/%/%/{node}")
    eps: dict[str, Endpoint] = {}
    for i, (topic, typ) in enumerate(spec["advertise"], start=1):
        h = rz.HUMBLE_HASH if mode == "humble" else ts.hash_rihs01(typ)
        eps[topic] = Endpoint(session, domain, node, i, topic, typ, h, spec.get("reliable", False),
                              buffer_aware=mode in ("rolling", "lyrical"))

    def on_token(sample):
        if sample.kind != zenoh.SampleKind.PUT:
            return
        ent = rz.parse_token(str(sample.key_expr))
        if ent is None or ent.kind != "MS" or ent.topic not in eps or ent.type != eps[ent.topic].entity.type:
            return
        say("MATCHED", sample.key_expr)
        eps[ent.topic].discover(ent)

    watch = live.declare_subscriber(rz.graph_key(domain), on_token, history=True)
    say("READY")
    # transient-local topics publish at once (a static_transform_publisher does): a later
    # subscription fetches them from the publisher's cache
    for topic, payload in spec.get("at_start", []):
        eps[topic].put(payload)
    if mode not in ("rolling", "lyrical") and not spec.get("go_at_once"):
        line = sys.stdin.readline()
        if line.strip() != "go":
            return
    want = int(spec.get("min_subscribers", 0))  # a test that needs that many subscriptions first
    for ep in {eps[step[1]] for step in spec["script"]}:
        end = time.monotonic() + 120
        while len(ep.seen) < want and time.monotonic() < end:
            time.sleep(0.01)
        if want and not ep.wait_matched(60):
            say("NO_SUBSCRIBER", ep.entity.topic)
            return
    sent: dict[str, int] = {}
    for step in spec["script"]:
        topic = step[1]
        ep = eps[topic]
        if mode in ("rolling", "lyrical") and not ep.wait_matched(60):
            say("NO_SUBSCRIBER", topic)
            return
        if step[0] == "skip":
            ep.skip()
        else:
            ep.put(step[2])
            sent[topic] = sent.get(topic, 0) + 1
        time.sleep(spec.get("period_s", 0.005))
    for topic, n in sent.items():
        say("SENT", topic, n)
    if spec.get("linger_s") is not None:  # started without a pipe on stdin (a namespace test)
        time.sleep(float(spec["linger_s"]))
    else:
        sys.stdin.read()  # stay in the graph (and keep the caches) until the test is done
    watch.undeclare()
    node_tok.undeclare()
    session.close()


if __name__ == "__main__":
    if sys.argv[1] == "--router":
        router(sys.argv[2])
    else:
        with open(sys.argv[1], "rb") as f:
            publish(pickle.load(f))
