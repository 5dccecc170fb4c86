"""pointflow: stream live point clouds through separate processes to the GPU."""
from __future__ import annotations

from ._lazy import lazy_exports
from .chunk import ChunkError, PointChunk
from .config import ConfigError, PipelineConfig, load_config
from .errors import Error, KeyedError
# the two one-call faces, imported at once (both are light): each module is named as the
# function it holds, and importing it first keeps ``pointflow.connect`` / ``pointflow.show``
# the functions (a submodule imported later would otherwise replace the name)
from .connect import LinkRefused, connect
from .show import show

__version__ = "0.1.0"

# Heavy parts (shared memory, zmq, GPU) load on first use.
__getattr__ = lazy_exports(__name__, {
    "Pipeline": ".runtime.pipeline", "PointRing": ".ring",
    # the errors users catch, all subclasses of Error (pointflow/errors.py)
    "PipelineFailed": ".runtime.supervisor", "SendError": ".ingest.transports.api",
    "ControlError": ".render.view.protocol", "PlaybackError": ".ingest.playback",
    "FormatError": ".formats", "MapError": ".map.errors", "RenderError": ".render.base",
    "RingError": ".ring.layout",
})

#: The errors a user of pointflow may catch (every one a subclass of :class:`Error`).
ERRORS = ("Error", "KeyedError", "ConfigError", "ChunkError", "SendError", "PipelineFailed", "ControlError",
          "PlaybackError", "LinkRefused", "FormatError", "MapError", "RenderError", "RingError")

__all__ = ["Pipeline", "connect", "show", "PointChunk", "PointRing", "PipelineConfig", "load_config",
           "__version__", *ERRORS]
