"""The ``zenoh:`` block shared by every end of a Zenoh link: ``send: {engine: zenoh}``, the
``zenoh`` and ``ros2_zenoh`` source transports and ``pointflow router`` (whose ``router:``
block, :class:`RouterConfig`, is one too).

Zenoh (https://zenoh.io) is the engine between hosts: peers, clients that connect to
routers, routers that fan out and cross networks, TLS with mutual authentication. This
module turns the block into a ``zenoh.Config`` and opens the session, so the three ends
cannot disagree about what a key means.

Safe by default, as the ZeroMQ links are: no multicast scouting unless asked, endpoints
on loopback unless configured, and a ``tcp``/``udp``/``quic`` endpoint on another host
without TLS is refused at load unless ``insecure: true``. Endpoints are Zenoh locators
(``tcp/127.0.0.1:7447``, ``tls/host:7447``, ``unixsock-stream/path``).
"""
from __future__ import annotations

import dataclasses
import ipaddress
import json
import os
import re
from dataclasses import field
from typing import TYPE_CHECKING, Any, Literal, Optional

from ..errors import Error
from ..typed import ConfigError, Each, Prefix, check, positive

if TYPE_CHECKING:  # zenoh is imported where a session opens: a config check needs no engine
    import zenoh

#: Zenoh locator schemes (the part before the first ``/``).
LOCATOR = Prefix(("tcp/", "tls/", "udp/", "quic/", "ws/", "unixsock-stream/", "unixpipe/", "vsock/", "serial/"),
                 "a Zenoh locator such as tcp/127.0.0.1:7447 or tls/host:7447")
#: Schemes that carry points in the clear across hosts.
_CLEAR = ("tcp/", "udp/", "ws/")
#: Schemes that are encrypted and authenticated by TLS.
_TLS = ("tls/", "quic/")

HOW_TO_TLS = ("make certificates with `pointflow keys NAME --tls --dir certs` (one CA, one certificate per "
              "host), use tls/HOST:PORT endpoints and set zenoh.tls.root_ca, zenoh.tls.certificate and "
              "zenoh.tls.private_key on every end; see docs/remote.md. Or set zenoh.insecure: true to send "
              "points unauthenticated and in the clear")


@dataclasses.dataclass
class ZenohTls:
    """TLS of a Zenoh session: one CA that signed every host's certificate."""

    #: The CA certificate (PEM) that signed the peers' certificates.
    root_ca: str = ""
    #: This end's certificate (PEM), presented when it listens and, with mutual, when it connects.
    certificate: str = ""
    #: This end's private key (PEM).
    private_key: str = ""
    #: Mutual authentication: both ends present a certificate signed by root_ca.
    mutual: bool = True
    #: Check that the certificate's name matches the host connected to.
    verify_name: bool = True


@dataclasses.dataclass
class ZenohOptions:
    """One Zenoh session (docs/remote.md)."""

    #: peer: talks to other peers directly; client: only through the routers in connect;
    #: router: routes for others (``pointflow router``).
    mode: Literal["peer", "client", "router"] = "peer"
    #: Locators to connect to (routers, or a peer that listens).
    connect: list[str] = field(default_factory=list, metadata=check(Each(LOCATOR)))
    #: Locators to listen on. Empty: the end's own default (see the end's docs).
    listen: list[str] = field(default_factory=list, metadata=check(Each(LOCATOR)))
    #: Find peers and routers by UDP multicast on the local network (off: only connect).
    scouting: bool = False
    #: A Zenoh config file (JSON5) for everything else (access control, QUIC, SHM sizes);
    #: the options above override its keys.
    config_file: str = ""
    tls: Optional[ZenohTls] = None
    #: Allow clear-text endpoints on other hosts (no TLS).
    insecure: bool = False


def _host_of(locator: str) -> str:
    rest = locator.split("/", 1)[1].split("#", 1)[0]
    return rest.rsplit(":", 1)[0].strip("[]")


def is_loopback_locator(locator: str) -> bool:
    """True for unix sockets and for tcp/udp/quic/tls on 127.0.0.0/8, ::1 or localhost."""
    if not locator.startswith(("tcp/", "udp/", "quic/", "tls/", "ws/")):
        return True
    host = _host_of(locator)
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a host name or a wildcard address


def _abs(p: str, base_dir: str) -> str:
    return p if not p or os.path.isabs(p) else os.path.normpath(os.path.join(base_dir, p))


def check_zenoh(o: ZenohOptions, path: str, base_dir: str, *, listen_default: tuple[str, ...] = (),
                connect_default: tuple[str, ...] = ()) -> None:
    """Resolve paths (in place), fill the end's default endpoints, and refuse what is unsafe
    or cannot work, naming the key."""
    if not o.listen and not o.connect:
        o.listen, o.connect = list(listen_default), list(connect_default)
    if o.mode == "client" and not o.connect and not o.scouting:
        raise ConfigError(f"{path}.connect", "a client reaches the network only through routers: give their "
                          "locators (e.g. [tcp/192.0.2.10:7447]) or set scouting: true")
    o.config_file = _abs(o.config_file, base_dir)
    if o.config_file and not os.path.isfile(o.config_file):
        raise ConfigError(f"{path}.config_file", f"no such file: {o.config_file}")
    if o.tls is not None:
        for key in ("root_ca", "certificate", "private_key"):
            p = _abs(getattr(o.tls, key), base_dir)
            setattr(o.tls, key, p)
            if key == "root_ca" and not p:
                raise ConfigError(f"{path}.tls.root_ca", "TLS needs the CA certificate that signed the peers' "
                                  "certificates (`pointflow keys NAME --tls` writes ca.pem)")
            if p and not os.path.isfile(p):
                raise ConfigError(f"{path}.tls.{key}", f"no such file: {p}")
        needs_own = o.tls.mutual or any(loc.startswith(_TLS) for loc in o.listen)
        if needs_own and not (o.tls.certificate and o.tls.private_key):
            raise ConfigError(f"{path}.tls.certificate", "this end must present a certificate and its "
                              "private_key (mutual TLS, or it listens on tls/)")
    for key in ("listen", "connect"):
        for i, loc in enumerate(getattr(o, key)):
            if loc.startswith(_TLS) and o.tls is None:
                raise ConfigError(f"{path}.{key}[{i}]", f"{loc} is a TLS endpoint but {path}.tls is not set. "
                                  f"To fix: {HOW_TO_TLS}")
            if loc.startswith(_CLEAR) and not o.insecure and not is_loopback_locator(loc):
                raise ConfigError(f"{path}.{key}[{i}]", f"{loc} is reachable from other hosts and carries "
                                  f"points in the clear: anyone on the network could read or inject them. "
                                  f"To fix: {HOW_TO_TLS}")
    if o.scouting and not o.insecure and o.tls is None:
        raise ConfigError(f"{path}.scouting", "multicast scouting connects to whatever answers on the local "
                          f"network; use it with TLS (tls endpoints) or set insecure: true. To fix: {HOW_TO_TLS}")


#: Zenoh settings every pointflow end uses unless its config_file sets them: Zenoh's own
#: default queue (2 batches of 64 KiB per priority) drops bursts of point chunks on a busy
#: host even on loopback (measured: 106 of 200 24-KB puts arrived at load 4); 16 batches
#: (1 MiB) held all 200 in every try. The receive buffer of each link is 1 MiB instead of
#: one 64 KiB batch: a 130-KB chunk arrives in three batches, and the larger buffer cut the
#: receiver's CPU time per chunk by about a tenth in bench/bench_remote.py --zenoh
#: (docs/remote.md, "The Zenoh engine"); larger TCP socket buffers did not help.
LINK_DEFAULTS: dict[str, Any] = {"transport/link/tx/queue/size/data": 16,
                                 "transport/link/rx/buffer_size": 1 << 20}


def zenoh_config(o: ZenohOptions, defaults: Optional[dict[str, Any]] = None) -> "zenoh.Config":
    """The ``zenoh.Config`` of a checked block. ``defaults`` (JSON paths, and
    :data:`LINK_DEFAULTS`) apply where the config file left Zenoh's default value."""
    import zenoh

    conf = zenoh.Config.from_file(o.config_file) if o.config_file else zenoh.Config()

    def put(key: str, value: Any) -> None:
        conf.insert_json5(key, json.dumps(value))

    if defaults is not None or LINK_DEFAULTS:
        builtin = zenoh.Config()
        for key, value in {**LINK_DEFAULTS, **(defaults or {})}.items():
            if conf.get_json(key) == builtin.get_json(key):
                put(key, value)

    if not o.config_file:
        # Zenoh's shared-memory transport (on by default) keeps a file in /dev/shm per
        # process, which a killed process leaves behind; pointflow's links cross hosts and its
        # local data already travel through its own ring, so it is off unless a config file
        # says otherwise (docs/remote.md).
        put("transport/shared_memory/enabled", False)
    put("mode", o.mode)
    put("connect/endpoints", list(o.connect))
    put("listen/endpoints", list(o.listen))
    put("scouting/multicast/enabled", bool(o.scouting))
    if o.tls is not None:
        t = o.tls
        put("transport/link/tls/root_ca_certificate", t.root_ca)
        if t.certificate:
            put("transport/link/tls/listen_certificate", t.certificate)
            put("transport/link/tls/listen_private_key", t.private_key)
        if t.mutual:
            put("transport/link/tls/enable_mtls", True)
            put("transport/link/tls/connect_certificate", t.certificate)
            put("transport/link/tls/connect_private_key", t.private_key)
        put("transport/link/tls/verify_name_on_connect", bool(t.verify_name))
    return conf


class ZenohOpenError(Error, RuntimeError):
    """A session could not open; the message says which endpoint and why."""


def open_session(o: ZenohOptions) -> "zenoh.Session":
    """Open a session for a checked block; an engine error becomes one readable line."""
    import zenoh

    try:
        return zenoh.open(zenoh_config(o))
    except zenoh.ZError as exc:
        where = ", ".join([f"listen {x}" for x in o.listen] + [f"connect {x}" for x in o.connect]) or "no endpoints"
        why = re.sub(r"\s+at /\S+\.rs:\d+\.?", "", str(exc))  # the engine's source locations: no help here
        raise ZenohOpenError(f"zenoh session ({o.mode}; {where}) did not open: {why}") from None


#: Where a router listens when the config names no endpoint: this host only.
DEFAULT_LISTEN = ("tcp/127.0.0.1:7447",)
#: A closing sender's query "did everything I put reach you?" carries these parameters; the
#: ``zenoh`` source answers it (``remote.zenoh_sender.confirm_delivery``).
CONFIRM_PARAMETERS = "pointflow=delivered"


@dataclasses.dataclass
class RouterConfig(ZenohOptions):
    """``router:`` block: the Zenoh router ``pointflow router`` runs (docs/remote.md).

    ``listen`` defaults to tcp/127.0.0.1:7447; ``connect`` names other routers to mesh with."""

    mode: Literal["router"] = "router"
    #: ``pointflow router`` prints the connected sessions this often (each session that
    #: opens, closes or is refused is logged when it happens).
    stats_every_s: float = field(default=5.0, metadata=check(positive))


def check_router(r: RouterConfig, path: str, base_dir: str) -> None:
    """Fill the default endpoint and run the checks every Zenoh end runs."""
    if not r.listen:
        r.listen = list(DEFAULT_LISTEN)
    check_zenoh(r, path, base_dir)
