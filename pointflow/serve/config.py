"""The ``serve:`` block (and ``pointflow run --serve [HOST:]PORT``): where the view server
listens and what it allows. Only :mod:`pointflow.typed` and the view protocol's limits
(:mod:`pointflow.render.view.protocol`, a config-level module) are imported here, so
``pointflow.config`` can hold a :class:`ServeConfig` without an import cycle.

Safe by default: loopback only; a random token is required (docs/views.md). A non-loopback
address needs TLS (``tls.cert`` and ``tls.key``, e.g. from ``pointflow keys NAME --tls``) or
an explicit ``insecure: true``; otherwise the config is refused at load, naming the key."""
from __future__ import annotations

import ipaddress
import os
import re
from dataclasses import dataclass, field
from typing import Optional

from ..render.view.protocol import MAX_VIEW_PX
from ..typed import Bound, ConfigError, at_least_one, check, positive


@dataclass
class ServeTlsConfig:
    """PEM files (``pointflow keys NAME --tls`` writes ``NAME.pem`` and ``NAME-key.pem``)."""

    cert: str = ""
    key: str = ""


@dataclass
class ServeLimits:
    """Bounds on what one client may cost (each breach is counted in ``stats()``)."""

    #: Clients at once; one more is refused (HTTP 503) and counted ``refused_full``.
    max_clients: int = field(default=64, metadata=check(at_least_one))
    #: A WebSocket message from a client larger than this closes that client (``bad_message``).
    max_message_bytes: int = field(default=16384, metadata=check(Bound(256, 1 << 20)))
    #: Messages per second a client may send (a 2 s burst is allowed); beyond it the
    #: client is closed (``rate_limited``).
    max_messages_per_s: float = field(default=200.0, metadata=check(positive))
    #: Encoded frames waiting for one client; a newer frame replaces the oldest (``dropped_frames``).
    queue_frames: int = field(default=2, metadata=check(Bound(1, 16)))
    #: A send to a client that takes longer than this closes it (a client that never reads).
    send_timeout_s: float = field(default=10.0, metadata=check(positive))
    #: The kernel's send buffer per client (SO_SNDBUF): what a client that stops reading can
    #: hold before its sends block (and it is closed after send_timeout_s).
    socket_buffer_bytes: int = field(default=262144, metadata=check(Bound(16384, 1 << 26)))
    #: The largest view a client may ask for (pixels per side; at most the render stage's).
    max_view_px: int = field(default=MAX_VIEW_PX, metadata=check(Bound(16, MAX_VIEW_PX)))
    #: A connection must have sent its request's headers within this long, and an idle
    #: keep-alive connection is closed after it: slow or silent connections hold nothing.
    header_timeout_s: float = field(default=10.0, metadata=check(Bound(0.5, 300)))


@dataclass
class ServeConfig:
    """``serve:``: the view server stage (pointflow/serve/, docs/views.md)."""

    #: Address to listen on; ``127.0.0.1`` (loopback) unless told otherwise.
    host: str = "127.0.0.1"
    #: TCP port; 0 = any free port (the ``view:`` line says which).
    port: int = field(default=8765, metadata=check(Bound(0, 65535)))
    #: The access token; null = a random one per run (printed once in the ``view:`` URL).
    token: Optional[str] = None
    tls: Optional[ServeTlsConfig] = None
    #: Listen on a non-loopback address without TLS (anyone on the path can watch and steer).
    insecure: bool = False
    #: Extra origins (``https://host:port``) whose pages may open the WebSocket; the page's
    #: own origin is always allowed.
    allowed_origins: list[str] = field(default_factory=list)
    #: Extra names the page may be reached under (the ``Host`` header: ``name`` or
    #: ``name:port``, e.g. a reverse proxy's). IP addresses, ``localhost``, the bound address
    #: and (listening on every address) this machine's name are always served; any other
    #: name is refused, so a DNS-rebinding page cannot reach the server under its own name.
    allowed_hosts: list[str] = field(default_factory=list)
    #: Size of a new view when the page does not say (it sends its own size).
    width: int = field(default=800, metadata=check(Bound(16, MAX_VIEW_PX)))
    height: int = field(default=600, metadata=check(Bound(16, MAX_VIEW_PX)))
    #: JPEG quality of moving frames at full size (still frames are PNG, lossless).
    jpeg_quality: int = field(default=80, metadata=check(Bound(1, 100)))
    #: Frames/s a moving view keeps on a slow link: its frames get a lower JPEG quality and
    #: then half or a quarter of the size until they fit (render/view/adapt.py); 0 = always full.
    adapt_fps: float = field(default=20.0, metadata=check(Bound(0, 240)))
    #: Threads that encode frames (off the render loop; the encoders release the GIL).
    encode_threads: int = field(default=2, metadata=check(Bound(1, 32)))
    limits: ServeLimits = field(default_factory=ServeLimits)


_TOKEN = re.compile(r"^[A-Za-z0-9_-]{16,128}$")
_HOST = re.compile(r"^(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9]([A-Za-z0-9.-]{0,252}))(:[0-9]{1,5})?$")


#: A DNS name: labels of letters, digits and '-', joined by dots.
_NAME_RE = re.compile(r"[A-Za-z0-9]([A-Za-z0-9-]*[A-Za-z0-9])?(\.[A-Za-z0-9]([A-Za-z0-9-]*[A-Za-z0-9])?)*\.?")


def _is_host(h: str) -> bool:
    """An IP address or a DNS name: what a socket can bind; a space or a scheme is a typo,
    not a host "reachable from other hosts"."""
    try:
        ipaddress.ip_address(h.split("%", 1)[0])
        return True
    except ValueError:
        return bool(_NAME_RE.fullmatch(h)) and len(h) <= 253


def is_loopback_host(host: str) -> bool:
    h = host.strip("[]")
    if h == "localhost":
        return True
    try:
        return ipaddress.ip_address(h).is_loopback
    except ValueError:
        return False  # a host name or "0.0.0.0": reachable from elsewhere


def check_serve(sc: ServeConfig, path: str, base_dir: str = ".") -> None:
    """Load-time checks; resolves the TLS paths against ``base_dir`` (in place)."""
    if not sc.host or not sc.host.strip():
        raise ConfigError(f"{path}.host", "must be an address to listen on, e.g. 127.0.0.1")
    if not _is_host(sc.host.strip("[]")):
        raise ConfigError(f"{path}.host", f"expected an IP address or a host name to listen on (e.g. 127.0.0.1, "
                                          f"0.0.0.0, ::1, robot.local), got {sc.host!r}")
    if sc.token is not None and not _TOKEN.match(sc.token):
        raise ConfigError(f"{path}.token", "must be 16-128 letters, digits, '-' or '_' (or null for a random one)")
    if sc.tls is not None:
        for k in ("cert", "key"):
            p = getattr(sc.tls, k)
            if not p:
                raise ConfigError(f"{path}.tls.{k}", "must name a PEM file (pointflow keys NAME --tls writes them)")
            p = p if os.path.isabs(p) else os.path.normpath(os.path.join(base_dir, p))
            setattr(sc.tls, k, p)
            if not os.path.isfile(p):
                raise ConfigError(f"{path}.tls.{k}", f"no such file: {p}")
    if sc.tls is None and not sc.insecure and not is_loopback_host(sc.host):
        raise ConfigError(f"{path}.insecure", f"{sc.host} is reachable from other hosts and the view server would "
                          "send the picture and take control unencrypted; give serve.tls.cert and serve.tls.key "
                          "(pointflow keys NAME --tls writes them) or set serve.insecure: true")
    for i, o in enumerate(sc.allowed_origins):
        if not re.match(r"^https?://[^/\s]+$", o):
            raise ConfigError(f"{path}.allowed_origins[{i}]", f"expected scheme://host[:port], got {o!r}")
    for i, h in enumerate(sc.allowed_hosts):
        if not isinstance(h, str) or not _HOST.match(h):
            raise ConfigError(f"{path}.allowed_hosts[{i}]", f"expected a host name or name:port (no scheme, no "
                              f"path), e.g. view.example.org or view.example.org:443, got {h!r}")


def parse_serve_arg(text: str) -> tuple[Optional[str], int]:
    """``--serve [HOST:]PORT`` -> (host or None, port); ValueError with a one-line reason."""
    host, sep, port = text.rpartition(":")
    try:
        p = int(port)
    except ValueError:
        raise ValueError(f"--serve: expected [HOST:]PORT, got {text!r}") from None
    if not 0 <= p <= 65535:
        raise ValueError(f"--serve: port {p} is not in 0..65535")
    return (host.strip("[]") or None) if sep else None, p


def with_serve(cfg, arg: str):
    """The config with ``--serve [HOST:]PORT`` applied over its ``serve:`` block (checked)."""
    import dataclasses

    host, port = parse_serve_arg(arg)
    sc = dataclasses.replace(cfg.serve) if cfg.serve is not None else ServeConfig()
    sc.port = port
    if host is not None:
        sc.host = host
    check_serve(sc, "serve", cfg.base_dir)
    return dataclasses.replace(cfg, serve=sc)
