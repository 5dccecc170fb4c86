"""The wire conventions of ROS 2's ``rmw_zenoh`` (ros2/rmw_zenoh, ``rmw_zenoh_cpp``), written
from its released sources, so the ``ros2_zenoh`` transport can talk to ROS 2 nodes without ROS.

* **Topic key expression** (``liveliness::TopicInfo``): ``<domain_id>/<topic>/<type>/<type hash>``,
  the topic without its leading and trailing ``/`` (``0/ouster/points/...``), the type in its
  DDS spelling (``sensor_msgs::msg::dds_::PointCloud2_``) and the type hash as
  ``RIHS01_<64 hex>`` (Iron and later) or ``TypeHashNotSupported`` (Humble). Subscriptions
  here put ``*`` in the hash chunk, so both match.
* **Payload**: the message in CDR with its 4-byte encapsulation header (``00 01 00 00`` for
  little-endian CDR), exactly what rosbags' ``deserialize_cdr`` reads.
* **Attachment** of every sample (``attachment_helpers.cpp``), in Zenoh's own serialisation
  (``zenoh::ext::Serializer``): int64 sequence number (1, 2, 3... per publisher), int64 source
  timestamp (ns since the epoch), then the publisher GID as a sequence of bytes (LEB128 length
  16, then 16 bytes). Earlier development builds wrote the same values each after a string
  key (``"sequence_number"``...); both are read.
* **Liveliness tokens** (``liveliness_utils.cpp``), one per node and endpoint, the ROS graph:
  ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/<node name>``
  and for publishers (``MP``) and subscriptions (``MS``) also
  ``/<topic>/<type>/<type hash>/<qos>``; ``/`` inside a name is written ``%`` (so the root
  namespace is ``%`` and ``/ouster/points`` is ``%ouster%points``). The QoS chunk is
  ``reliability:durability:history,depth:deadline s,ns:lifespan s,ns:liveliness,lease s,ns``,
  each value left empty when it is rmw_zenoh's default (reliable, volatile, keep last, 42).
  The GID of an entity is XXH3-128 of its token (low 64 bits, then high, little-endian).
* **Buffer-aware topics** (rmw_zenoh 0.10.5 on Lyrical, 0.12.0 on Rolling, ros2/rmw_zenoh#930:
  ``buffer_endpoint_helpers.hpp``, ``rmw_publisher_data.cpp``, ``rmw_subscription_data.cpp``,
  ``liveliness_utils.cpp``, ``graph_cache.cpp``): for a type whose typesupport has buffer fields
  (PointCloud2's ``uint8[] data``), publisher and subscription tokens end with a 14th chunk
  ``backends:<name>:<metadata>[;...]`` (sorted by name, ``% ; : /`` escaped as ``%25 %3B %3A
  %2F``); a publisher always includes ``cpu``, so its token ends ``backends:cpu:``. Once it has
  discovered every matched subscription (each subscription token on the topic name), a publisher
  puts nothing on the base key: subscriptions whose backends are exactly ``{cpu}`` get plain CDR
  on ``<base key>/_buf_cpu`` (one put), every other one (including a token without backends) its
  own put on ``<base key>/_buf/<subscription GID hex>``, each put with the next sequence number.
  With no subscription discovered it sends nothing.

No zenoh import here (the parts are plain strings and bytes), except where an attachment is
read or written with Zenoh's serialiser.
"""
from __future__ import annotations

import dataclasses
import re
from typing import Any, Mapping, Optional

from ..errors import Error

#: Prefix of every rmw_zenoh liveliness token.
ADMIN_SPACE = "@ros2_lv"
#: The type-hash chunk Humble's rmw_zenoh writes.
HUMBLE_HASH = "TypeHashNotSupported"
KINDS = {"NN": "node", "MP": "publisher", "MS": "subscription", "SS": "service", "SC": "client"}

#: rmw QoS enum values (rmw/types.h)
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST = 1
_DEFAULT = {"reliability": RELIABLE, "durability": VOLATILE, "history": KEEP_LAST, "depth": 42}

_ROS_TYPE = re.compile(r"^([A-Za-z0-9_]+)/(msg|srv|action)/([A-Za-z0-9_]+)$")
_DDS_TYPE = re.compile(r"^([A-Za-z0-9_]+)::(msg|srv|action)::dds_::([A-Za-z0-9_]+)_$")


def dds_type(ros_type: str) -> str:
    """``sensor_msgs/msg/PointCloud2`` -> ``sensor_msgs::msg::dds_::PointCloud2_``."""
    m = _ROS_TYPE.match(ros_type)
    if not m:
        raise ValueError(f"not a ROS 2 type name (pkg/msg/Name): {ros_type!r}")
    return f"{m.group(1)}::{m.group(2)}::dds_::{m.group(3)}_"


def ros_type(dds: str) -> str:
    """The reverse of :func:`dds_type`; a name that is not in DDS spelling is returned as is."""
    m = _DDS_TYPE.match(dds)
    return f"{m.group(1)}/{m.group(2)}/{m.group(3)}" if m else dds


def topic_key(domain_id: int, topic: str, ros_type_name: str, type_hash: str = "*") -> str:
    """The key expression data of ``topic`` is put on (``type_hash='*'``: any distribution)."""
    return f"{int(domain_id)}/{topic.strip('/')}/{dds_type(ros_type_name)}/{type_hash}"


#: The backends a CPU-only buffer-aware subscription declares (rmw_subscription_data.cpp: no
#: acceptable_buffer_backends given -> ``{"cpu": ""}``).
CPU_ONLY = {"cpu": ""}
#: Types whose typesupport has buffer fields (rosidl sets ``has_buffer_fields``; rmw_zenoh only
#: reads it): the top-level ``uint8[]`` of PointCloud2. Transient-local endpoints never use them.
BUFFER_TYPES = frozenset({"sensor_msgs/msg/PointCloud2"})


def buffer_cpu_key(base_key: str) -> str:
    """Where a buffer-aware publisher puts for CPU-only subscriptions (``make_cpu_group_key``)."""
    return f"{base_key}/_buf_cpu"


def buffer_key(base_key: str, subscription_gid: bytes) -> str:
    """Where it puts for one other subscription (``make_accelerated_key``, GID in lowercase hex)."""
    return f"{base_key}/_buf/{bytes(subscription_gid).hex()}"


def gid(token_key: str) -> bytes:
    """An entity's 16-byte GID: XXH3-128 of its token (``Entity::Entity``: memcpy of the low
    then the high 64 bits, little-endian machines)."""
    import xxhash

    return xxhash.xxh3_128(token_key.encode()).intdigest().to_bytes(16, "little")


def _escape_backend(text: str) -> str:
    return "".join({"%": "%25", ";": "%3B", ":": "%3A", "/": "%2F"}.get(c, c) for c in text)


def _unescape_backend(text: str) -> str:
    return re.sub(r"%([0-9A-Fa-f]{2})", lambda m: chr(int(m.group(1), 16)), text)


def backends_chunk(backends: Mapping[str, str]) -> str:
    """``{"cpu": ""}`` -> ``backends:cpu:`` (names sorted, fields escaped)."""
    return "backends:" + ";".join(f"{_escape_backend(n)}:{_escape_backend(backends[n])}" for n in sorted(backends))


def parse_backends(chunk: str) -> Optional[dict[str, str]]:
    """The reverse of :func:`backends_chunk`; None for a chunk that is not one (or lists none)."""
    if not chunk.startswith("backends:"):
        return None
    out = {}
    for entry in chunk[len("backends:"):].split(";"):
        if entry:
            name, _, meta = entry.partition(":")
            if name:
                out[_unescape_backend(name)] = _unescape_backend(meta)
    return out or None


def mangle(name: str) -> str:
    return name.replace("/", "%")


def demangle(name: str) -> str:
    return name.replace("%", "/")


def qos_chunk(reliability: int = RELIABLE, durability: int = VOLATILE, depth: int = 42) -> str:
    """The QoS part of a liveliness token, defaults left empty as rmw_zenoh writes them."""
    def v(key: str, val: int) -> str:
        return "" if val == _DEFAULT[key] else str(val)
    return f"{v('reliability', reliability)}:{v('durability', durability)}:,{v('depth', depth)}:,:,:,,"


@dataclasses.dataclass(frozen=True)
class Entity:
    """One liveliness token of the ROS graph."""

    domain_id: int
    zid: str
    node_id: str
    entity_id: str
    kind: str                  # NN, MP, MS, SS, SC
    enclave: str
    namespace: str
    node: str
    topic: str = ""            # with its leading "/"
    type: str = ""             # ROS spelling, sensor_msgs/msg/PointCloud2
    type_hash: str = ""
    qos: str = ""
    #: Buffer backends (rmw_zenoh 0.10.5+/0.12.0+, buffer-aware types only); None: no chunk.
    backends: Optional[dict[str, str]] = dataclasses.field(default=None, hash=False)

    @property
    def buffer_aware(self) -> bool:
        return bool(self.backends)

    @property
    def cpu_only(self) -> bool:
        """A subscription a buffer-aware publisher serves on ``_buf_cpu`` (backends exactly cpu)."""
        return self.backends == CPU_ONLY

    @property
    def durability(self) -> int:
        parts = self.qos.split(":")
        return int(parts[1]) if len(parts) > 1 and parts[1].isdigit() else VOLATILE

    def key(self) -> str:
        """The token's key expression (as rmw_zenoh's ``Entity`` builds it)."""
        parts = [ADMIN_SPACE, str(self.domain_id), self.zid, self.node_id, self.entity_id, self.kind,
                 mangle(self.enclave), mangle(self.namespace), mangle(self.node)]
        if self.kind != "NN":
            parts += [mangle(self.topic), mangle(dds_type(self.type)), mangle(self.type_hash), self.qos]
            if self.backends:
                parts.append(backends_chunk(self.backends))
        return "/".join(parts)

    def gid(self) -> bytes:
        return gid(self.key())


def parse_token(key: str) -> Optional[Entity]:
    """A liveliness key expression -> :class:`Entity`; None for anything that is not a
    well-formed rmw_zenoh token (other tools share the admin space)."""
    parts = str(key).split("/")
    if len(parts) < 9 or parts[0] != ADMIN_SPACE or parts[5] not in KINDS or not all(parts[:9]):
        return None
    try:
        domain = int(parts[1])
    except ValueError:
        return None
    common = dict(domain_id=domain, zid=parts[2], node_id=parts[3], entity_id=parts[4], kind=parts[5],
                  enclave=demangle(parts[6]), namespace=demangle(parts[7]), node=demangle(parts[8]))
    if parts[5] == "NN":
        return Entity(**common)
    if len(parts) < 13 or not all(parts[9:12]):
        return None
    backends = parse_backends(parts[13]) if len(parts) > 13 else None
    return Entity(**common, topic=demangle(parts[9]), type=ros_type(demangle(parts[10])),
                  type_hash=demangle(parts[11]), qos=parts[12], backends=backends)


def graph_key(domain_id: int) -> str:
    """Every token of one domain (what rmw_zenoh's graph cache subscribes to)."""
    return f"{ADMIN_SPACE}/{int(domain_id)}/**"


# ----------------------------------------------------------------------------- attachment
@dataclasses.dataclass(frozen=True)
class Attachment:
    sequence_number: int
    source_timestamp_ns: int
    gid: bytes

    @property
    def gid_hex(self) -> str:
        return self.gid.hex()


class AttachmentError(Error, ValueError):
    """A sample without a readable rmw_zenoh attachment."""


def _zbytes(raw: Any):
    import zenoh
    return raw if isinstance(raw, zenoh.ZBytes) else zenoh.ZBytes(bytes(raw))


def parse_attachment(raw: Any) -> Attachment:
    """A sample's attachment (``zenoh.ZBytes`` or bytes) -> :class:`Attachment`; raises
    :class:`AttachmentError`. Reads the released layout (int64, int64, byte sequence) and the
    earlier keyed one (each value after its name)."""
    from zenoh.ext import Int64, ZDeserializeError, z_deserialize

    if raw is None:
        raise AttachmentError("the sample has no attachment (not from rmw_zenoh?)")
    zb = _zbytes(raw)
    legacy = zb.to_bytes().startswith(b"\x0fsequence_number")
    try:
        if legacy:
            k1, seq, k2, stamp, k3, gid = z_deserialize(tuple[str, Int64, str, Int64, str, bytes], zb)
            if (k1, k2, k3) != ("sequence_number", "source_timestamp", "source_gid"):
                raise AttachmentError(f"keyed attachment with unexpected keys {k1!r}, {k2!r}, {k3!r}")
        else:
            seq, stamp, gid = z_deserialize(tuple[Int64, Int64, bytes], zb)
    except (ZDeserializeError, ValueError, TypeError, UnicodeDecodeError) as exc:
        if isinstance(exc, AttachmentError):
            raise
        raise AttachmentError(f"attachment of {len(zb.to_bytes())} bytes is not rmw_zenoh's "
                              "(int64 sequence number, int64 source time, GID bytes)") from None
    if len(gid) not in (16, 24):
        raise AttachmentError(f"publisher GID of {len(gid)} bytes (16 expected)")
    return Attachment(int(seq), int(stamp), bytes(gid))


def encode_attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes):
    """The released layout, as ``zenoh.ZBytes`` (what an rmw_zenoh publisher attaches)."""
    from zenoh.ext import Int64, z_serialize

    return z_serialize((Int64(sequence_number), Int64(source_timestamp_ns), bytes(gid)))


# ----------------------------------------------------------------------------- loss accounting
class SequenceLedger:
    """Messages lost in transit per publisher, from the attachments' sequence numbers.

    A publisher numbers its messages 1, 2, 3...; a gap between two that arrive is that many
    messages lost on the way (or dropped by a congested Zenoh link, as rmw_zenoh's publishers
    drop rather than block). What was sent before the first message seen here is not loss
    (``joined_after``); a number at or below one already seen (a duplicate, or a reordered
    message) is counted as ``out_of_order`` and still delivered."""

    def __init__(self) -> None:
        self.last: dict[tuple[str, str], int] = {}
        self.lost: dict[tuple[str, str], int] = {}
        self.received: dict[tuple[str, str], int] = {}
        self.joined_after: dict[tuple[str, str], int] = {}
        self.min_step: dict[tuple[str, str], int] = {}
        self.out_of_order = 0

    def observe(self, topic: str, att: Attachment, stride: int = 0) -> int:
        """Account one message; returns how many were lost just before it.

        ``stride`` (a message that came on ``_buf_cpu``): a buffer-aware publisher numbers
        every put, and puts each message once on ``_buf_cpu`` and once more per other
        subscription it has discovered (and it never forgets one that left), so steps are
        ``1 + those``. The stride used is the larger of ``stride`` (from the graph now) and the
        smallest step this publisher has shown on that path; a step that is not a whole number
        of strides is rounded down: loss is never overstated. 0: a plain path, step 1."""
        k = (topic, att.gid_hex)
        seq = att.sequence_number
        last = self.last.get(k)
        if stride and last is not None and seq > last:
            self.min_step[k] = min(self.min_step.get(k, seq - last), seq - last)
        stride = max(1, int(stride), self.min_step.get(k, 1) if stride else 1)
        self.received[k] = self.received.get(k, 0) + 1
        if last is None:
            self.last[k] = seq
            self.lost.setdefault(k, 0)
            self.joined_after[k] = max(0, seq - 1) // stride
            return 0
        if seq <= last:
            self.out_of_order += 1
            return 0
        gap = (seq - last) // stride - 1
        self.lost[k] += gap
        self.last[k] = seq
        return gap

    def counters(self) -> dict[str, int]:
        """Flat numbers for stats: ``lost_in_transit_messages`` and, per publisher,
        ``lost_in_transit_messages:<topic>@<gid hex>``."""
        out = {"lost_in_transit_messages": sum(self.lost.values()), "publishers_seen": len(self.last),
               "out_of_order": self.out_of_order, "joined_after_messages": sum(self.joined_after.values())}
        for (topic, gid), n in sorted(self.lost.items()):
            out[f"lost_in_transit_messages:{topic}@{gid}"] = n
        return out
