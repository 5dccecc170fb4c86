"""The transport adapter API: what a plugin implements.

A transport runs inside its own source process. The source loop calls ``open()``,
then iterates ``chunks()`` and pushes every :class:`PointChunk` to ingest over ZeroMQ,
then calls ``close()``. ``chunks()`` may yield ``None`` when nothing is ready, so the
loop can send heartbeats and notice a stop request; it must not block for longer than
about 100 ms at a time.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from abc import ABC, abstractmethod
from typing import Any, Callable, ClassVar, Iterator, Optional

from ...chunk import ChunkError, PointChunk
from ...errors import Error
from ...typed import ConfigError, load_dataclass


class InputUnreadable(Error):
    """None of a transport's input can be read (every file of a replay is unreadable):
    restarting cannot help, so the source stage reports it and the run fails (exit 2),
    with this message naming the inputs and why."""


@dataclasses.dataclass
class NoOptions:
    """For transports that take no options."""


class Transport(ABC):
    #: Name used in YAML (``transport: NAME``) and in logs.
    name: ClassVar[str] = ""
    #: A dataclass whose fields are the accepted options (validated at config load).
    options_schema: ClassVar[type] = NoOptions
    #: True for replays (files, as-fast-as-possible generators): when ingest is behind the
    #: source waits instead of dropping chunks. Live transports leave it False.
    lossless: bool = False
    #: Field names a decoding transport keeps whatever its channel filter says: the source
    #: stage sets the per-point time fields here before ``open()`` when deskew is on
    #: (docs/frames.md). A transport may also yield
    #: :class:`pointflow.frames.message.Transforms` between chunks (docs/plugins.md).
    keep_fields: tuple[str, ...] = ()
    #: True when ingest places points in a fixed frame (``frames.fixed``): a transport that
    #: can subscribe to transforms (rosbridge's /tf) does so only then. Set before ``open()``.
    wants_transforms: bool = False
    #: The ring's ``max_points``, set by the source stage before ``open()``: a replay can say
    #: when it sends more than the ring holds (the ``file`` transport does). None outside a run.
    ring_capacity: Optional[int] = None

    #: True for replays whose ``playback`` (a :class:`pointflow.ingest.playback.PlaybackClock`)
    #: can be paused, sought, stepped, sped up and looped from Python (docs/api.md).
    seekable: ClassVar[bool] = False
    playback: Any = None

    def __init__(self, options: dict[str, Any], source_id: str):
        self.options = options
        self.source_id = source_id
        #: Counters shown in stats (for example ``reconnects``); numbers only.
        self.counters: dict[str, float] = {}

    @classmethod
    def validate_options(cls, options: Any, path: str, base_dir: str = ".") -> dict[str, Any]:
        """Check ``options`` against :attr:`options_schema`; errors name ``path.key``.

        Returns a plain dict (picklable) with defaults filled in. Override
        :meth:`check_options` for checks beyond types."""
        who = f"transport {cls.name or cls.__name__!r} ({cls.__module__}.{cls.__qualname__})"
        try:
            obj = load_dataclass(cls.options_schema, options if options is not None else {}, path)
            cls.check_options(obj, path, base_dir)
        except ConfigError as exc:
            raise ConfigError(exc.path, f"{_msg(exc)} [{who}]") from None
        except Exception as exc:  # noqa: BLE001 - a plugin's checks can fail in any way
            raise ConfigError(path, f"{who} failed to check its options: {type(exc).__name__}: {exc}") from None
        return dataclasses.asdict(obj)

    @classmethod
    def check_options(cls, opts: Any, path: str, base_dir: str) -> None:
        """Semantic checks; raise ``ConfigError(f"{path}.key", ...)``."""

    @classmethod
    def declared_channels(cls, options: dict[str, Any], base_dir: str = ".") -> Optional[frozenset[str]]:
        """The channels this source's chunks carry, when the (validated) options tell without
        waiting for data; None when only the data will. ``render.color_by`` naming a channel
        that no source declares is refused at load (config.py)."""
        return None

    @property
    def opts(self):
        """Options as the schema dataclass (attribute access)."""
        return self.options_schema(**self.options)

    def reject(self, reason: str, message: str) -> None:
        """Count a malformed message (``rejected`` and ``rejected_<reason>`` in stats) and
        log it, at most once per reason every 5 s."""
        self.counters["rejected"] = self.counters.get("rejected", 0) + 1
        key = f"rejected_{reason}"
        self.counters[key] = self.counters.get(key, 0) + 1
        now = time.monotonic()
        last = self.__dict__.setdefault("_reject_logged", {})
        if now - last.get(reason, -1e9) >= 5.0:
            last[reason] = now
            logging.getLogger(f"pointflow.transport.{self.name or type(self).__name__}").warning(
                "%s: rejected message [%s]: %s", self.source_id, reason, message)

    def accept(self, parse: Callable[[Any], PointChunk], message: Any) -> Optional[PointChunk]:
        """``parse(message)``, or None when it is malformed: a :class:`ChunkError` is rejected
        with its reason, anything else as ``decode_error``; a bad message never ends the stream."""
        try:
            return parse(message)
        except ChunkError as exc:
            self.reject(exc.reason, str(exc))
        except Exception as exc:  # noqa: BLE001 - never let a message kill the source
            self.reject("decode_error", f"{type(exc).__name__}: {exc}")
        return None

    def quota_reached(self) -> bool:
        """Count one chunk handed out; True once ``max_chunks`` (an option of the network
        transports, 0 = never) have been, so ``chunks()`` can return."""
        self._handed_out = getattr(self, "_handed_out", 0) + 1
        limit = self.options.get("max_chunks", 0) or 0
        return bool(limit) and self._handed_out >= limit

    def open(self) -> None:
        """Connect, open files; raise an exception with a clear message on failure."""

    @abstractmethod
    def chunks(self) -> Iterator[Optional[PointChunk]]:
        """Yield chunks as they arrive (``None`` when idle). Return when the stream ends."""

    def close(self) -> None:
        """Release sockets and files. Called on every exit path."""


def _msg(exc) -> str:
    """A ConfigError's message without its ``path: `` prefix."""
    return exc.message
