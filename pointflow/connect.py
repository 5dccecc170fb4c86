"""``pointflow.connect``: send clouds from this process to a pipeline in another process or
on another host, over the links of ``pointflow send`` (docs/remote.md, docs/api.md).

``connect(endpoint, **link_options)`` is ``pointflow send`` with one ``api`` source: the
same config (``send:`` takes ``endpoint`` and the link options, checked by the same loader,
so an unsafe endpoint or a missing key file is refused with the same message), the same
sender stage (CURVE and its ZAP handshake, or Zenoh with TLS; the link sequence that lets
the receiver count ``lost_in_transit``; its bounded queue), started as a child process.
The caller's clouds go to that stage through an in-process ``api`` source, exactly as
``Pipeline.send`` feeds ingest.
"""
from __future__ import annotations

import os
import time
from typing import Any, Literal, Optional

from .config import load_config
from .errors import Error

#: How often ``send`` looks at the link's state (a refused handshake, a failed sender).
CHECK_EVERY_S = 0.25


class LinkRefused(Error, ConnectionRefusedError):
    """The receiving end refused this end's key; the message is the one ``pointflow send``
    logs for the same refusal."""


class Sender:
    """What :func:`connect` returns: ``send``/``send_transforms`` as on a Pipeline, ``stats()``,
    ``close()`` (also on ``with``)."""

    def __init__(self, pipeline, source: str, endpoint: str):
        self._p = pipeline
        self.source = source
        self.endpoint = endpoint
        self._next_check = 0.0

    def send(self, positions, *, frame: Optional[str] = None, stamp_ns: Optional[int] = None, **channels) -> int:
        """As :meth:`pointflow.Pipeline.send`; raises :class:`LinkRefused` once the receiver
        refused this end's key."""
        self._check_link()
        return self._p.send(positions, source=self.source, frame=frame, stamp_ns=stamp_ns, **channels)

    def send_transforms(self, transforms) -> int:
        """As :meth:`pointflow.Pipeline.send_transforms`."""
        self._check_link()
        return self._p.send_transforms(transforms, source=self.source)

    @property
    def refusal(self) -> str:
        """The link's last refusal message ("" while none)."""
        return str(self._p.stats().get("stages", {}).get("sender", {}).get("link_refusal", ""))

    def _check_link(self) -> None:
        now = time.monotonic()
        if now < self._next_check:
            return
        self._next_check = now + CHECK_EVERY_S
        if not self._p.running:
            self._p.poll(0)  # raises PipelineFailed with the sender stage's reason
            raise RuntimeError(f"the link to {self.endpoint} is closed")
        refusal = self.refusal
        if refusal:
            raise LinkRefused(refusal)

    def stats(self) -> dict[str, Any]:
        """The send run's numbers (``accounting``: sources, ``sender_received`` = ``link_sent``
        + ``sender_dropped`` + queued), as in ``pointflow send``'s stats.json."""
        return self._p.stats()

    def close(self) -> dict:
        """Hand what was accepted to the link (the sender flushes its queue and the final
        link sync), stop the sender; returns the final stats. Idempotent."""
        return self._p.stop()

    def __enter__(self) -> "Sender":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def connect(endpoint: Optional[str], *, source: str = "api", backpressure: Literal["block", "drop_oldest"] = "block",
            queue_clouds: int = 8, base_dir: Optional[str] = None, **link_options) -> Sender:
    """Open a link to ``endpoint`` with ``link_options`` (the rest of ``send:``:
    ``curve_secret_key``, ``curve_server_key``, ``socket``, ``bind``, ``engine``, ``key``,
    ``zenoh``, ``compression``, ``insecure``, ...; docs/remote.md) and return a
    :class:`Sender`. ZeroMQ (default): ``endpoint`` is ``send.endpoint``. Zenoh
    (``engine="zenoh"``): ``endpoint`` is a locator (``tcp/host:port``) added to
    ``zenoh.connect`` (None: only the ``zenoh`` block's own). Clouds are tagged with ``source`` (the name the receiver counts them
    under). Relative key paths are taken from ``base_dir`` (default: the working
    directory). Raises :class:`pointflow.ConfigError` naming the option on a bad or unsafe
    option, before anything starts."""
    from .runtime.pipeline import Pipeline

    send = dict(link_options)
    if send.get("engine") == "zenoh":
        # the endpoint is a Zenoh locator (tcp/host:port) this end connects to
        if endpoint:
            z = dict(send.get("zenoh") or {})
            z["connect"] = [endpoint, *z.get("connect", [])]
            send["zenoh"] = z
    else:
        send["endpoint"] = endpoint
    data = {
        "name": "connect",
        "sources": [{"transport": "api", "name": source,
                     "options": {"backpressure": backpressure, "queue_clouds": queue_clouds}}],
        "send": send,
        "tracing": {"enabled": False},
        "render": {"output": {"dir": None}},
    }
    cfg = load_config(data, base_dir=base_dir or os.getcwd())
    p = Pipeline(cfg, out_dir="", role="send")
    p.start()
    return Sender(p, source, endpoint)


__all__ = ["connect", "Sender", "LinkRefused"]
