"""pointflow: stream live point clouds through separate processes to the GPU."""
from __future__ import annotations

from .chunk import ChunkError, PointChunk
from .config import ConfigError, PipelineConfig, load_config

__version__ = "0.1.0"


def __getattr__(name: str):
    # Heavy parts (shared memory, zmq, GPU) load on first use.
    if name == "Pipeline":
        from .runtime.pipeline import Pipeline

        return Pipeline
    if name == "connect":
        from .client import connect

        return connect
    if name == "show":
        from .quickshow import show

        return show
    if name == "SendError":
        from .ingest.transports.api import SendError

        return SendError
    if name == "PointRing":
        from .ring import PointRing

        return PointRing
    raise AttributeError(name)


__all__ = ["Pipeline", "connect", "show", "SendError", "PointChunk", "PointRing", "ChunkError", "ConfigError", "PipelineConfig", "load_config", "__version__"]
