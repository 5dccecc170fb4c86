"""Frames: where every point is in the world (docs/frames.md).

A tf2-like transform buffer (:mod:`.buffer`), per-point motion compensation
(:mod:`.deskew`), the ``frames:`` config block (:mod:`.config`), the transforms wire
message (:mod:`.message`), the point loops (:mod:`.kernels`: a rigid transform, which the
ring may also apply as it writes) and the ingest step that uses them (:mod:`.framer`). Nothing
here imports the ingest package: ingest imports frames, never the other way round.
"""
from .buffer import FrameError, NoTransform, TransformBuffer
from .message import Transform, Transforms

__all__ = ["FrameError", "NoTransform", "TransformBuffer", "Transform", "Transforms"]
