"""Getting points in: the source stage, the ingest stage (the ring's only writer) and
the readers and decoders they use.

* :mod:`.source_process`: the source stage (one transport in its own process, pushing chunks);
  :mod:`.transports`: the adapter API (:class:`~.transports.Transport`), the built-ins and
  plugin resolution (:func:`~.transports.resolve_transport`);
* :mod:`.process`: the ingest stage and :class:`Ingestor` (decode, validate, convert,
  coalesce, push, with exact counters);
* decoders and readers: :mod:`.jsonchunk`, :mod:`.quantised`, :mod:`.formats`
  (:func:`~.formats.read_points`: LAS/LAZ, PLY, PCD, NPZ, KITTI, text),
  :mod:`.pointcloud2`, :mod:`.rostf`, :mod:`.rmw_zenoh`; :mod:`.playback` (pause, seek,
  rate and loop of a replay).
"""
from .._lazy import lazy_exports

__getattr__ = lazy_exports(__name__, {
    "Ingestor": ".process", "Transport": ".transports", "resolve_transport": ".transports",
    "read_points": ".formats", "PlaybackConfig": ".playback",
})

__all__ = ["Ingestor", "PlaybackConfig", "Transport", "read_points", "resolve_transport"]
