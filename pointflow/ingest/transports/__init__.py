"""Transport adapters: built-ins, the ``pointflow.transports`` entry-point group and
``package.module:Class`` plugins, resolved by :func:`resolve_transport`."""
from __future__ import annotations

import importlib
from importlib import metadata

from ...typed import ConfigError
from .base import NoOptions, Transport

#: Built-in transports: name -> "module:Class" (imported lazily).
BUILTINS: dict[str, str] = {
    "synthetic": "pointflow.ingest.transports.synthetic:SyntheticTransport",
    "zmq": "pointflow.ingest.transports.zmq_transport:ZmqTransport",
    "zenoh": "pointflow.ingest.transports.zenoh_transport:ZenohTransport",
    "websocket": "pointflow.ingest.transports.websocket:WebSocketTransport",
    "sse": "pointflow.ingest.transports.sse:SseTransport",
    "file": "pointflow.ingest.transports.file:FileTransport",
    "rosbag": "pointflow.ingest.transports.rosbag:RosbagTransport",
    "rosbridge": "pointflow.ingest.transports.rosbridge:RosbridgeTransport",
    "ros2_zenoh": "pointflow.ingest.transports.ros2_zenoh:Ros2ZenohTransport",
    "api": "pointflow.ingest.transports.api:ApiTransport",
}

ENTRY_POINT_GROUP = "pointflow.transports"


def _load_target(target: str, what: str) -> type[Transport]:
    mod_name, _, attr = target.partition(":")
    try:
        mod = importlib.import_module(mod_name)
    except Exception as exc:  # noqa: BLE001 - a plugin can fail in any way
        hint = ""
        if isinstance(exc, ModuleNotFoundError) and exc.name == mod_name.split(".")[0]:
            import os

            here = os.path.exists(mod_name.split(".")[0] + ".py") or os.path.isdir(mod_name.split(".")[0])
            hint = (" (it is in the working directory, which the pointflow command does not import from: "
                    "run with PYTHONPATH=. or pip install it)" if here else
                    " (install it, or put its folder on PYTHONPATH)")
        raise ConfigError("", f"transport plugin {what} failed to import module {mod_name!r}: "
                              f"{type(exc).__name__}: {exc}{hint}") from None
    try:
        cls = getattr(mod, attr) if attr else None
    except AttributeError:
        cls = None
    if cls is None:
        raise ConfigError("", f"transport plugin {what}: module {mod_name!r} has no attribute {attr!r}")
    if not (isinstance(cls, type) and issubclass(cls, Transport)):
        raise ConfigError("", f"transport plugin {what}: {target} is not a pointflow Transport subclass")
    missing = sorted(getattr(cls, "__abstractmethods__", ()))
    if missing:  # refused at load: it could only fail in every start of its stage
        raise ConfigError("", f"transport plugin {what}: {target} does not define {', '.join(m + '()' for m in missing)} "
                              f"(docs/plugins.md)")
    return cls


def entry_point_transports() -> dict[str, metadata.EntryPoint]:
    return {ep.name: ep for ep in metadata.entry_points(group=ENTRY_POINT_GROUP)}


def resolve_transport(spec: str) -> type[Transport]:
    """A built-in name, an entry-point name, or ``package.module:Class``."""
    if spec in BUILTINS:
        return _load_target(BUILTINS[spec], repr(spec))
    if ":" in spec:
        return _load_target(spec, repr(spec))
    eps = entry_point_transports()
    if spec in eps:
        return _load_target(eps[spec].value, f"{spec!r} (entry point {eps[spec].value})")
    known = sorted(set(BUILTINS) | set(eps))
    raise ConfigError("", f"unknown transport {spec!r}; expected one of {', '.join(known)} or 'package.module:Class'")


def runs_in_process(spec: str) -> bool:
    """A transport that lives in the process holding the pipeline (``api``: fed by
    ``Pipeline.send``), which the supervisor keeps in its stage table instead of starting."""
    if spec == "api":
        return True
    try:
        return bool(getattr(resolve_transport(spec), "in_process", False))
    except Exception:  # noqa: BLE001 - the config loader already checked it resolves
        return False


def available_transports() -> dict[str, str]:
    """name -> where it comes from, for ``pointflow info``."""
    out = {n: "built-in" for n in BUILTINS}
    for n, ep in entry_point_transports().items():
        try:
            _load_target(ep.value, repr(n))
            out[n] = f"plugin ({ep.value})"
        except ConfigError as exc:  # listed, and why it cannot be used
            out[n] = f"plugin ({ep.value}), does not load: {exc.message.split(': ', 1)[-1]}"
    return out


__all__ = ["Transport", "NoOptions", "resolve_transport", "runs_in_process", "available_transports", "BUILTINS", "ENTRY_POINT_GROUP"]
