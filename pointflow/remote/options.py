"""The options of a network link, shared by the sending end (``send:``) and the receiving
``zmq`` transport, and the safe-default check both run at config load.

The end that binds is the CURVE server: it has its own secret key and a folder of the
client public keys it accepts. The end that connects is the client: its own secret key and
the server's public key. A ``tcp://`` endpoint on anything but a loopback address needs
CURVE, unless ``insecure: true`` says the user wants it in the clear.
"""
from __future__ import annotations

import dataclasses
import ipaddress
import os
from dataclasses import field
from typing import Literal, Optional

from ..typed import Bound, ConfigError, at_least_one, check, endpoint, non_negative, positive
from .keys import KeyFileError, authorized_keys, load_public, load_secret
from .zenoh_options import ZenohOptions, check_zenoh

HOW_TO_KEYS = ("create keys with `pointflow keys NAME --dir keys` on each host, then set curve_secret_key "
               "(this end's NAME.key_secret) and, on the connecting end, curve_server_key (the binding "
               "end's public NAME.key), on the binding end curve_authorized_keys (a folder of the "
               "connecting ends' public .key files); see docs/remote.md. Or set insecure: true to send "
               "points unauthenticated and in the clear")


@dataclasses.dataclass
class LinkOptions:
    """Security and liveness of one ZeroMQ link."""

    #: This end's ``NAME.key_secret`` (turns CURVE on).
    curve_secret_key: str = ""
    #: Connecting end: the binding end's public ``NAME.key``.
    curve_server_key: str = ""
    #: Binding end: folder of the public ``.key`` files of the peers it accepts.
    curve_authorized_keys: str = ""
    #: Allow a tcp:// endpoint on a non-loopback address without CURVE.
    insecure: bool = False
    #: ZeroMQ heartbeats: PING every interval; a peer silent for timeout is dropped; ttl
    #: tells the peer to drop us after that long. 0 = off.
    heartbeat_ivl_s: float = field(default=1.0, metadata=check(non_negative))
    heartbeat_timeout_s: float = field(default=3.0, metadata=check(non_negative))
    heartbeat_ttl_s: float = field(default=3.0, metadata=check(Bound(0, 6553, note="ZeroMQ's limit")))


@dataclasses.dataclass
class SendConfig(LinkOptions):
    """``send:`` section: where ``pointflow send`` publishes the sources' chunks."""

    #: zmq: a ZeroMQ socket (endpoint, socket, CURVE keys); zenoh: a Zenoh session publishing
    #: each source on key ``<key>/<source>`` (zenoh block; docs/remote.md "The Zenoh engine").
    engine: Literal["zmq", "zenoh"] = "zmq"
    endpoint: str = field(default="tcp://127.0.0.1:5556", metadata=check(endpoint))
    #: pub: every connected viewer gets every chunk (fan-out); push: one receiver per chunk.
    socket: Literal["pub", "push"] = "pub"
    bind: bool = True
    #: ZeroMQ send high-water mark (messages per peer). PUB drops for a peer at this mark.
    send_hwm: int = field(default=16, metadata=check(at_least_one))
    #: Kernel send buffer of the link socket (KiB; 0 = the OS default, often megabytes).
    #: Small keeps a thin link's backlog in the sender's queue, where the oldest is dropped,
    #: instead of seconds of stale data in the kernel.
    send_buffer_kb: int = field(default=256, metadata=check(non_negative))
    #: The sender's own queue (chunks); when the link is slower than the sensor the oldest
    #: chunk is dropped (``link_queue_full``) so the sensor never waits.
    queue_chunks: int = field(default=64, metadata=check(at_least_one))
    #: true: with the queue full, stop taking chunks from the sources instead (replays then
    #: wait; live sources drop at their own send queue, counted as ``hwm``).
    backpressure: bool = False
    compression: Literal["none", "lz4", "zstd"] = "none"
    #: 0 = the codec's default (lz4 0, zstd 3).
    compression_level: int = 0
    #: Byte-shuffle frames before compressing (better ratios on numbers).
    shuffle: bool = True
    #: Quantise positions to this resolution (metres, e.g. 0.001); 0 = send floats.
    quantise: float = field(default=0.0, metadata=check(non_negative))
    #: Send a sync (per-source totals) this often, so receivers see losses at the tail.
    sync_every_s: float = field(default=0.5, metadata=check(positive))
    #: Before sending, wait for this many subscribers (pub) for at most wait_s. Zenoh engine:
    #: any number > 0 waits until every configured source's key has a subscriber (Zenoh
    #: tells whether one matches, not how many).
    wait_subscribers: int = field(default=0, metadata=check(non_negative))
    wait_s: float = field(default=10.0, metadata=check(non_negative))
    reconnect_initial_s: float = field(default=0.1, metadata=check(non_negative))
    reconnect_max_s: float = field(default=5.0, metadata=check(non_negative))
    #: engine zenoh: the key prefix; source S is published on ``<key>/S``.
    key: str = "pointflow"
    #: engine zenoh: the session (mode, endpoints, TLS); listens on tcp/127.0.0.1:7448 by default.
    zenoh: Optional[ZenohOptions] = None


#: Keys of ``send:`` that only the ZeroMQ engine reads; the Zenoh engine's own.
ZMQ_ONLY = ("endpoint", "socket", "bind", "send_hwm", "send_buffer_kb",
            "curve_secret_key", "curve_server_key", "curve_authorized_keys", "insecure", "heartbeat_ivl_s",
            "heartbeat_timeout_s", "heartbeat_ttl_s", "reconnect_initial_s", "reconnect_max_s")
ZENOH_ONLY = ("key", "zenoh")


def _engine_rule() -> dict:
    """check_send's engine rule in JSON Schema: each engine's keys keep their defaults under the other."""
    d = {f.name: f.default for f in dataclasses.fields(SendConfig)}
    keep = lambda keys: {"properties": {k: {"const": d[k]} for k in keys}}  # noqa: E731
    return {"if": {"properties": {"engine": {"const": "zenoh"}}, "required": ["engine"]},
            "then": keep(ZMQ_ONLY), "else": keep(ZENOH_ONLY)}


SendConfig.json_schema_extra = _engine_rule()
#: Where a Zenoh sender listens unless its zenoh block says otherwise (a receiver's default connect).
ZENOH_SEND_LISTEN = "tcp/127.0.0.1:7448"
_BAD_KEY_CHARS = set("*$?#")


def check_key_expr(key: str, path: str, wildcards: bool) -> None:
    """A Zenoh key expression: chunks separated by ``/``, none empty; ``*``, ``**`` only where
    ``wildcards``; never ``$``, ``?``, ``#``."""
    chunks = key.split("/")
    bad = next((c for c in chunks if not c or (set(c) & _BAD_KEY_CHARS and not (wildcards and c in ("*", "**")))), None)
    if bad is not None:
        what = "an empty chunk (a leading, trailing or double /)" if not bad else f"the chunk {bad!r}"
        allowed = "chunks, * and **" if wildcards else "chunks without *, $, ?, #"
        raise ConfigError(path, f"{key!r} is not a Zenoh key expression for this end: it has {what}; use {allowed} "
                          "separated by / (e.g. pointflow/site1)")


def source_key(prefix: str, source: str) -> str:
    """The key a sender publishes source ``source`` on (characters a key cannot hold become _)."""
    safe = "".join("_" if ch in _BAD_KEY_CHARS else ch for ch in source).strip("/") or "source"
    safe = "/".join(c or "_" for c in safe.split("/"))
    return f"{prefix}/{safe}"


def is_loopback_endpoint(endpoint: str) -> bool:
    """True for ipc://, inproc:// and tcp:// on 127.0.0.0/8, ::1 or localhost."""
    if not endpoint.startswith(("tcp://", "pgm://", "epgm://")):
        return True
    host = endpoint.split("://", 1)[1].rsplit(":", 1)[0]
    if ";" in host:  # tcp://source;dest: the remote part decides
        host = host.split(";", 1)[1]
    host = host.strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # "*", an interface name or a host name


def _abs(p: str, base_dir: str) -> str:
    return p if not p or os.path.isabs(p) else os.path.normpath(os.path.join(base_dir, p))


def check_link_options(o: LinkOptions, path: str, endpoint: str, bind: bool, base_dir: str) -> None:
    """Resolve key paths against ``base_dir`` (in place) and check them; refuse a
    non-loopback tcp:// link without CURVE unless ``insecure``."""
    o.curve_secret_key = _abs(o.curve_secret_key, base_dir)
    o.curve_server_key = _abs(o.curve_server_key, base_dir)
    o.curve_authorized_keys = _abs(o.curve_authorized_keys, base_dir)
    if o.curve_secret_key:
        try:
            load_secret(o.curve_secret_key)
        except KeyFileError as exc:
            raise ConfigError(f"{path}.curve_secret_key", str(exc)) from None
        if bind:
            if o.curve_server_key:
                raise ConfigError(f"{path}.curve_server_key", "the binding end is the CURVE server: it takes "
                                  "curve_authorized_keys (the clients' public keys), not curve_server_key")
            if not o.curve_authorized_keys:
                raise ConfigError(f"{path}.curve_authorized_keys", "the binding end needs a folder of the public "
                                  "keys it accepts (the connecting ends' NAME.key files)")
            try:
                authorized_keys(o.curve_authorized_keys)
            except KeyFileError as exc:
                raise ConfigError(f"{path}.curve_authorized_keys", str(exc)) from None
        else:
            if o.curve_authorized_keys:
                raise ConfigError(f"{path}.curve_authorized_keys", "the connecting end is the CURVE client: it "
                                  "takes curve_server_key (the binding end's public key), not a keys folder")
            if not o.curve_server_key:
                raise ConfigError(f"{path}.curve_server_key", "the connecting end needs the binding end's "
                                  "public key file (NAME.key)")
            try:
                load_public(o.curve_server_key)
            except KeyFileError as exc:
                raise ConfigError(f"{path}.curve_server_key", str(exc)) from None
    elif o.curve_server_key or o.curve_authorized_keys:
        raise ConfigError(f"{path}.curve_secret_key", "CURVE needs this end's secret key file (NAME.key_secret)")
    elif not o.insecure and not is_loopback_endpoint(endpoint):
        raise ConfigError(f"{path}.endpoint", f"{endpoint} is reachable from other hosts and this link has no "
                          f"CURVE keys: anyone on the network could read or inject points. To fix: {HOW_TO_KEYS}")


def check_send(s: SendConfig, path: str, base_dir: str) -> None:
    """Semantic checks of a ``send:`` section (errors name the key)."""
    # bounds of single options are declared on the fields (check(...)), so the JSON Schema has them
    defaults = SendConfig()
    if s.engine == "zenoh":
        for key in ZMQ_ONLY:
            if getattr(s, key) != getattr(defaults, key):
                raise ConfigError(f"{path}.{key}", f"{key} is an option of the zmq engine; with engine: zenoh the "
                                  f"link is set in {path}.zenoh (mode, listen, connect, tls, insecure)")
        check_key_expr(s.key, f"{path}.key", wildcards=False)
        if s.zenoh is None:
            s.zenoh = ZenohOptions()
        if s.zenoh.mode == "router":
            raise ConfigError(f"{path}.zenoh.mode", "a sender is a peer or a client; run routers with `pointflow router`")
        check_zenoh(s.zenoh, f"{path}.zenoh", base_dir, listen_default=(ZENOH_SEND_LISTEN,))
    else:
        for key in ZENOH_ONLY:
            if getattr(s, key) != getattr(defaults, key):
                raise ConfigError(f"{path}.{key}", f"{key} is an option of the zenoh engine; set {path}.engine: zenoh "
                                  "to publish over Zenoh")
    if s.compression != "none":
        try:
            __import__("lz4.frame" if s.compression == "lz4" else "zstandard")
        except ImportError:
            raise ConfigError(f"{path}.compression", f"{s.compression} needs its Python package: "
                              "pip install 'pointflow[remote]'") from None
    if s.engine == "zenoh":
        return
    if s.wait_subscribers and s.socket != "pub":
        raise ConfigError(f"{path}.wait_subscribers", "only a pub socket has subscribers to wait for")
    check_link_options(s, path, s.endpoint, s.bind, base_dir)
