"""``rosbridge``: a live ``sensor_msgs/PointCloud2`` topic from a robot running rosbridge.

A rosbridge v2 protocol client over WebSocket (the ``websocket`` transport's client, with its
reconnect backoff). After every (re)connect it sends one ``subscribe``::

    {"op": "subscribe", "id": ..., "topic": ..., "type": "sensor_msgs/msg/PointCloud2",
     "throttle_rate": ..., "queue_length": ..., "compression": "cbor" | "none"}

``cbor`` makes the bridge send binary CBOR frames with ``data`` as a byte string (compact,
no base64); ``none`` sends JSON text with ``data`` in base64. Only ``publish`` messages for
the subscribed topic become chunks (decoded by :mod:`pointflow.ingest.pointcloud2`, stamped
with ``header.stamp``); ``status`` messages are logged and counted (``status``,
``status_<level>``); anything else is rejected with a reason and counted (``bad_json``,
``bad_cbor``, ``bad_shape``, ``unexpected_op``, ``wrong_topic`` and the decoder's reasons).
With ``frames.fixed`` set it also subscribes to ``tf_topics`` (``/tf``, ``/tf_static``) and
yields their ``tf2_msgs/TFMessage`` as transforms, in arrival order with the clouds
(docs/frames.md). On stop it sends ``unsubscribe``. Needs ``websockets`` and, for CBOR, ``cbor2``
(``pip install 'pointflow[network,ros]'``).
"""
from __future__ import annotations

import dataclasses
import itertools
import json
import logging
import os
from typing import Any, Literal, Optional

from ...chunk import ChunkError, PointChunk
from ...typed import ConfigError
from ...frames.message import Transforms
from ..pointcloud2 import MSGTYPES, PointCloud2Decoder
from ..rostf import decode_tf
from ._backoff import Backoff, NetworkOptions
from .base import Transport
from .websocket import WebSocketTransport

log = logging.getLogger("pointflow.transport.rosbridge")
_ids = itertools.count(1)


@dataclasses.dataclass
class RosbridgeOptions(NetworkOptions):
    #: The rosbridge server (rosbridge_websocket listens on 9090).
    url: str = "ws://127.0.0.1:9090"
    #: The PointCloud2 topic, e.g. /ouster/points.
    topic: str = ""
    #: ROS 2 name; the ROS 1 name sensor_msgs/PointCloud2 is accepted too.
    type: str = "sensor_msgs/msg/PointCloud2"
    #: Minimum ms between messages the bridge sends (0 = every message).
    throttle_rate: int = 0
    #: Messages the bridge buffers for us (1 = always the newest).
    queue_length: int = 1
    #: cbor: binary frames, data as bytes (recommended); none: JSON, data as base64.
    compression: Literal["cbor", "none"] = "cbor"
    #: Field renames, e.g. {reflectivity: intensity}.
    rename: dict[str, str] = dataclasses.field(default_factory=dict)
    #: Keep only these channels (after renaming); null = every field.
    channels: Optional[list[str]] = None
    #: tf2_msgs/TFMessage topics subscribed to when ``frames.fixed`` is set (docs/frames.md);
    #: a topic ending in ``_static`` holds static transforms.
    tf_topics: list[str] = dataclasses.field(default_factory=lambda: ["/tf", "/tf_static"])


class RosbridgeTransport(WebSocketTransport):
    name = "rosbridge"
    options_schema = RosbridgeOptions

    @classmethod
    def check_options(cls, o: RosbridgeOptions, path: str, base_dir: str) -> None:
        if not o.url.startswith(("ws://", "wss://")):
            raise ConfigError(f"{path}.url", f"must start with ws:// or wss://, got {o.url!r}")
        if not o.topic.startswith("/") or len(o.topic) < 2:
            raise ConfigError(f"{path}.topic", f"a ROS topic name starting with '/' is required, got {o.topic!r}")
        if o.type not in MSGTYPES:
            raise ConfigError(f"{path}.type", f"must be one of {', '.join(MSGTYPES)}, got {o.type!r}")
        if o.throttle_rate < 0:
            raise ConfigError(f"{path}.throttle_rate", "must be >= 0 ms")
        if o.queue_length < 1:
            raise ConfigError(f"{path}.queue_length", "must be >= 1")
        for key in ("reconnect_initial_s", "reconnect_max_s", "connect_timeout_s"):
            if getattr(o, key) <= 0:
                raise ConfigError(f"{path}.{key}", "must be > 0")
        if o.compression == "cbor":
            try:
                import cbor2  # noqa: F401
            except ImportError:
                raise ConfigError(f"{path}.compression", "cbor needs the 'cbor2' package: pip install 'pointflow[ros]' "
                                  "(or use compression: none)") from None

    def __init__(self, options: dict[str, Any], source_id: str):
        Transport.__init__(self, options, source_id)  # not WebSocketOptions: only the client is shared
        self.o = RosbridgeOptions(**options)
        self.decoder = PointCloud2Decoder(self.o.rename, self.o.channels)
        self.counters = {"connects": 0, "reconnects": 0, "messages": 0, "rejected": 0, "status": 0}
        self.sub_id = f"pointflow_{os.getpid()}_{next(_ids)}"
        self._ws = None
        self._backoff = Backoff(self.o.reconnect_initial_s, self.o.reconnect_max_s)
        self._cbor_loads = None
        if self.o.compression == "cbor":
            import cbor2
            self._cbor_loads = cbor2.loads

    def subscribe_message(self) -> dict[str, Any]:
        o = self.o
        return {"op": "subscribe", "id": self.sub_id, "topic": o.topic, "type": o.type,
                "throttle_rate": o.throttle_rate, "queue_length": o.queue_length, "compression": o.compression}

    def tf_subscribe_messages(self) -> list[dict[str, Any]]:
        """Subscriptions to the transform topics (only when the frames step is on)."""
        if not self.wants_transforms:
            return []
        typ = "tf2_msgs/msg/TFMessage" if "/msg/" in self.o.type else "tf2_msgs/TFMessage"
        return [{"op": "subscribe", "id": f"{self.sub_id}_tf{i}", "topic": t, "type": typ,
                 "queue_length": 100, "compression": self.o.compression} for i, t in enumerate(self.o.tf_topics)]

    def on_connect(self) -> None:
        if self.decoder.always != tuple(self.keep_fields):  # set by the source stage after __init__
            self.decoder = PointCloud2Decoder(self.o.rename, self.o.channels, always=self.keep_fields)
        try:
            self._ws.send(json.dumps(self.subscribe_message()))
            for m in self.tf_subscribe_messages():
                self._ws.send(json.dumps(m))
        except Exception as exc:  # noqa: BLE001 - the next recv notices the dead link and reconnects
            log.warning("%s: subscribe to %s failed: %s", self.source_id, self.o.topic, exc)

    def _load(self, msg: bytes | str) -> Any:
        if isinstance(msg, str) or msg[:1] == b"{":
            try:
                return json.loads(msg)
            except (UnicodeDecodeError, ValueError) as exc:
                raise ChunkError("bad_json", f"not valid JSON: {str(exc)[:120]}") from None
        if self._cbor_loads is None:
            try:
                import cbor2
            except ImportError:
                raise ChunkError("bad_cbor", "a binary (CBOR) frame arrived but cbor2 is not installed") from None
            self._cbor_loads = cbor2.loads
        try:
            return self._cbor_loads(msg)
        except Exception as exc:  # noqa: BLE001 - cbor2 raises CBORDecodeError and friends
            raise ChunkError("bad_cbor", f"not valid CBOR: {type(exc).__name__}: {str(exc)[:120]}") from None

    def parse(self, msg: bytes | str) -> Optional[PointChunk]:  # type: ignore[override]
        """One rosbridge frame -> chunk, None for a status message; raises ChunkError."""
        obj = self._load(msg)
        if not isinstance(obj, dict) or not isinstance(obj.get("op"), str):
            raise ChunkError("bad_shape", f"not a rosbridge message (an object with 'op'), got {type(obj).__name__}")
        op = obj["op"]
        if op == "status":
            level = str(obj.get("level", "info"))
            self.counters["status"] += 1
            key = f"status_{level}"
            self.counters[key] = self.counters.get(key, 0) + 1
            log.log(logging.WARNING if level in ("warning", "error") else logging.INFO,
                    "%s: rosbridge status [%s]: %s", self.source_id, level, str(obj.get("msg", ""))[:300])
            return None
        if op != "publish":
            raise ChunkError("unexpected_op", f"op {op!r} (only 'publish' and 'status' are expected)")
        if self.wants_transforms and obj.get("topic") in self.o.tf_topics:
            body = obj.get("msg")
            if not isinstance(body, dict):
                raise ChunkError("bad_shape", f"publish 'msg' must be an object, got {type(body).__name__}")
            topic = obj["topic"]
            batch = decode_tf(body, topic.endswith("_static"), f"{self.source_id}:{topic}")
            self.counters["transforms"] = self.counters.get("transforms", 0) + len(batch)
            return batch  # type: ignore[return-value]
        if obj.get("topic") != self.o.topic:
            raise ChunkError("wrong_topic", f"publish for topic {obj.get('topic')!r}, subscribed to {self.o.topic!r}")
        body = obj.get("msg")
        if not isinstance(body, dict):
            raise ChunkError("bad_shape", f"publish 'msg' must be an object, got {type(body).__name__}")
        chunk = self.decoder.decode(body, f"{self.source_id}:{self.o.topic}")
        if chunk.n > self.o.max_points:
            raise ChunkError("too_large", f"{chunk.n} points, more than max_points {self.o.max_points}")
        return chunk

    def close(self) -> None:
        if self._ws is not None:
            try:
                self._ws.send(json.dumps({"op": "unsubscribe", "id": self.sub_id, "topic": self.o.topic}))
                for m in self.tf_subscribe_messages():
                    self._ws.send(json.dumps({"op": "unsubscribe", "id": m["id"], "topic": m["topic"]}))
                self.counters["unsubscribed"] = 1
            except Exception:  # noqa: BLE001 - the link is gone: nothing to unsubscribe from
                pass
        super().close()
