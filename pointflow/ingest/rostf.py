"""``tf2_msgs/TFMessage`` -> :class:`~pointflow.frames.message.Transforms`: the one decoder
the ``rosbag`` and ``rosbridge`` transports use for ``/tf`` and ``/tf_static`` (ROS 1 and
ROS 2 spellings; rosbags objects or rosbridge dicts). Leading ``/`` of ROS 1 frame ids is
dropped, as tf2 does."""
from __future__ import annotations

from typing import Any

from ..chunk import ChunkError
from ..frames.message import Transform, Transforms
from .pointcloud2 import _get, stamp_ns

#: Type names a TFMessage goes by (ROS 2 and ROS 1 spelling).
TF_MSGTYPES = ("tf2_msgs/msg/TFMessage", "tf2_msgs/TFMessage")
DEFAULT_TF_TOPICS = ["/tf", "/tf_static"]


def _num(obj: Any, key: str, what: str) -> float:
    v = _get(obj, key)
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        try:
            return float(v)  # numpy scalars
        except (TypeError, ValueError):
            raise ChunkError("bad_transform", f"{what}.{key} must be a number, got {type(v).__name__}") from None
    return float(v)


def decode_tf(msg: Any, static: bool, source_id: str = "") -> Transforms:
    """Every TransformStamped of one TFMessage; raises :class:`ChunkError` (``bad_transform``)."""
    items = _get(msg, "transforms")
    if not isinstance(items, (list, tuple)):
        raise ChunkError("bad_transform", "TFMessage 'transforms' must be a list")
    out = []
    for i, ts in enumerate(items):
        w = f"transforms[{i}]"
        try:
            parent = str(_get(_get(ts, "header"), "frame_id")).lstrip("/")
            child = str(_get(ts, "child_frame_id")).lstrip("/")
            tr = _get(ts, "transform")
            t, r = _get(tr, "translation"), _get(tr, "rotation")
        except ChunkError as exc:
            raise ChunkError("bad_transform", f"{w}: {exc}") from None
        out.append(Transform(parent, child, stamp_ns(ts), tuple(_num(t, k, f"{w}.translation") for k in "xyz"),
                             tuple(_num(r, k, f"{w}.rotation") for k in "xyzw"), static))
    return Transforms(out, source_id)
