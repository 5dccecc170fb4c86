"""Transforms on the ingest socket: the ``pointflow.transforms/1`` message
(docs/wire-format.md) and the objects a transport yields for it (docs/plugins.md).

A transport's ``chunks()`` may yield a :class:`Transforms` between its chunks; the source
stage sends it on the same socket as the clouds, so ingest sees both in the order the
transport produced them. The message is one ZeroMQ frame of UTF-8 JSON::

    {"schema": "pointflow.transforms/1", "source": "bag",
     "transforms": [{"parent": "odom", "child": "base_link", "stamp_ns": 1700000000050000000,
                     "translation": [1.0, 2.0, 0.0], "rotation": [0, 0, 0.38268343, 0.92387953],
                     "static": false}, ...]}
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

from ..errors import Error

SCHEMA = "pointflow.transforms/1"
#: What ingest looks for in the first bytes of a one-frame message to tell it from a JSON chunk.
SCHEMA_BYTES = b'"pointflow.transforms/1"'
#: A transforms message larger than this is refused unparsed.
MAX_MESSAGE_BYTES = 4 << 20


class TransformMessageError(Error, ValueError):
    """A malformed transforms message; ``reason`` is counted by ingest."""

    def __init__(self, reason: str, message: str):
        super().__init__(f"{reason}: {message}")
        self.reason = reason
        self.message = message


@dataclass
class Transform:
    """parent <- child at ``stamp_ns`` (ns since the epoch; ROS time), rotation (x, y, z, w).

    It maps points given in ``child`` into ``parent``, as a ROS TransformStamped with
    ``header.frame_id = parent`` and ``child_frame_id = child``."""

    parent: str
    child: str
    stamp_ns: int
    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float]
    static: bool = False

    def to_json(self) -> dict[str, Any]:
        return {"parent": self.parent, "child": self.child, "stamp_ns": int(self.stamp_ns),
                "translation": [float(v) for v in self.translation],
                "rotation": [float(v) for v in self.rotation], "static": bool(self.static)}


@dataclass
class Transforms:
    """A batch of transforms a transport yields in its stream of chunks."""

    transforms: list[Transform] = field(default_factory=list)
    source_id: str = ""

    def __len__(self) -> int:
        return len(self.transforms)


def encode(batch: Transforms, source_id: str = "") -> list[bytes]:
    """One-frame message for ``send_multipart``."""
    body = {"schema": SCHEMA, "source": batch.source_id or source_id,
            "transforms": [t.to_json() for t in batch.transforms]}
    return [json.dumps(body, separators=(",", ":")).encode()]


def is_transforms(obj: Any) -> bool:
    return isinstance(obj, dict) and obj.get("schema") == SCHEMA


def _num_list(v: Any, n: int, what: str) -> tuple[float, ...]:
    if (not isinstance(v, list) or len(v) != n
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)):
        raise TransformMessageError("bad_transform", f"{what} must be a list of {n} numbers, got {v!r}"[:200])
    return tuple(float(x) for x in v)


def decode(obj: dict) -> Transforms:
    """A parsed message (``json.loads`` of the frame) -> :class:`Transforms`; raises
    :class:`TransformMessageError` (reason ``bad_transform``) naming the entry at fault."""
    items = obj.get("transforms")
    if not isinstance(items, list):
        raise TransformMessageError("bad_transform", "'transforms' must be a list")
    out = []
    for i, it in enumerate(items):
        w = f"transforms[{i}]"
        if not isinstance(it, dict):
            raise TransformMessageError("bad_transform", f"{w} must be an object")
        parent, child, stamp = it.get("parent"), it.get("child"), it.get("stamp_ns", 0)
        if not isinstance(parent, str) or not isinstance(child, str) or not parent or not child:
            raise TransformMessageError("bad_transform", f"{w} needs 'parent' and 'child' frame names")
        if not isinstance(stamp, int) or isinstance(stamp, bool) or stamp < 0:
            raise TransformMessageError("bad_transform", f"{w}.stamp_ns must be an integer >= 0, got {stamp!r}")
        static = it.get("static", False)
        if not isinstance(static, bool):
            raise TransformMessageError("bad_transform", f"{w}.static must be true or false")
        out.append(Transform(parent, child, stamp, _num_list(it.get("translation"), 3, f"{w}.translation"),
                             _num_list(it.get("rotation"), 4, f"{w}.rotation"), static))
    src = obj.get("source", "")
    return Transforms(out, src if isinstance(src, str) else "")
