"""The typed loader that config and every transport's options share: YAML-ish values →
dataclasses, with errors that name the key path (``render.size[0]``).

The bottom layer of configuration: it imports nothing of pointflow, so
:mod:`pointflow.config` and :mod:`pointflow.ingest.transports` can both import it and
imports run one way (config → transports → typed).
"""
from __future__ import annotations

import dataclasses
import types
import typing
from typing import Any, Literal, Union


class ConfigError(ValueError):
    """A configuration value is wrong; ``path`` is the dotted key path."""

    def __init__(self, path: str, message: str):
        super().__init__(f"{path or '<root>'}: {message}" if path else message)
        self.path = path


def positive(v, path):
    if v <= 0:
        raise ConfigError(path, f"must be > 0, got {v!r}")


def non_negative(v, path):
    if v < 0:
        raise ConfigError(path, f"must be >= 0, got {v!r}")


def at_least_one(v, path):
    if v < 1:
        raise ConfigError(path, f"must be >= 1, got {v!r}")


def endpoint(v, path):
    if v is None:
        return
    if not any(v.startswith(p) for p in ("ipc://", "tcp://", "inproc://")):
        raise ConfigError(path, f"must be a ZeroMQ endpoint (ipc://, tcp://), got {v!r}")


def check(fn):
    """Field metadata: a validator called with (value, path)."""
    return {"check": fn}



# --------------------------------------------------------------------------- loader
def type_name(tp) -> str:
    origin = typing.get_origin(tp)
    if origin is Literal:
        return " | ".join(repr(a) for a in typing.get_args(tp))
    if origin in (Union, types.UnionType):
        return " or ".join(type_name(a) for a in typing.get_args(tp))
    if origin is list:
        return f"list of {type_name(typing.get_args(tp)[0])}"
    if origin is dict:
        k, v = typing.get_args(tp)
        return f"mapping of {type_name(k)} to {type_name(v)}"
    if tp is type(None):
        return "null"
    return getattr(tp, "__name__", str(tp))


def convert(value: Any, tp: Any, path: str) -> Any:
    origin = typing.get_origin(tp)
    if tp is Any:
        return value
    if origin in (Union, types.UnionType):
        errors = []
        for alt in typing.get_args(tp):
            try:
                return convert(value, alt, path)
            except ConfigError as exc:
                errors.append(exc)
        alts = [e for a, e in zip(typing.get_args(tp), errors) if a is not type(None)]
        if value is not None and len(alts) == 1:  # Optional[X]: X's own error names the key inside
            raise alts[0]
        raise ConfigError(path, f"expected {type_name(tp)}, got {value!r}")
    if origin is Literal:
        choices = typing.get_args(tp)
        if value not in choices:
            raise ConfigError(path, f"must be one of {', '.join(map(str, choices))}; got {value!r}")
        return value
    if tp is type(None):
        if value is not None:
            raise ConfigError(path, f"expected null, got {value!r}")
        return None
    if dataclasses.is_dataclass(tp):
        return load_dataclass(tp, value, path)
    if origin is list:
        if not isinstance(value, list):
            raise ConfigError(path, f"expected a list, got {type(value).__name__} {value!r}")
        (item,) = typing.get_args(tp)
        return [convert(v, item, f"{path}[{i}]") for i, v in enumerate(value)]
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(path, f"expected a mapping, got {type(value).__name__} {value!r}")
        kt, vt = typing.get_args(tp)
        return {convert(k, kt, f"{path}.{k}"): convert(v, vt, f"{path}.{k}") for k, v in value.items()}
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(path, f"expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(path, f"expected an integer, got {type(value).__name__} {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(path, f"expected a number, got {type(value).__name__} {value!r}")
        if value != value or value in (float("inf"), float("-inf")):
            raise ConfigError(path, f"must be finite, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(path, f"expected a string, got {type(value).__name__} {value!r}")
        return value
    raise ConfigError(path, f"unsupported type {tp!r}")  # pragma: no cover


def load_dataclass(cls, data: Any, path: str):
    if not isinstance(data, dict):
        raise ConfigError(path, f"expected a mapping, got {type(data).__name__} {data!r}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if not f.metadata.get("internal")}
    unknown = [k for k in data if k not in fields]
    if unknown:
        key = unknown[0]
        raise ConfigError(join_path(path, str(key)), f"unknown key; expected one of {', '.join(fields)}")
    kwargs = {}
    for name, f in fields.items():
        p = join_path(path, name)
        if name in data:
            kwargs[name] = convert(data[name], hints[name], p)
            fn = f.metadata.get("check")
            if fn is not None and kwargs[name] is not None:
                fn(kwargs[name], p)
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError(p, "required key is missing")
    return cls(**kwargs)


def join_path(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key



# --------------------------------------------------------------------------- JSON Schema
def schema_of(tp: Any) -> dict:
    origin = typing.get_origin(tp)
    if tp is Any:
        return {}
    if origin in (Union, types.UnionType):
        return {"anyOf": [schema_of(a) for a in typing.get_args(tp)]}
    if origin is Literal:
        return {"enum": list(typing.get_args(tp))}
    if tp is type(None):
        return {"type": "null"}
    if dataclasses.is_dataclass(tp):
        return dataclass_schema(tp)
    if origin is list:
        return {"type": "array", "items": schema_of(typing.get_args(tp)[0])}
    if origin is dict:
        return {"type": "object", "additionalProperties": schema_of(typing.get_args(tp)[1])}
    return {"type": {bool: "boolean", int: "integer", float: "number", str: "string"}[tp]}


def dataclass_schema(cls) -> dict:
    hints = typing.get_type_hints(cls)
    props, required = {}, []
    for f in dataclasses.fields(cls):
        if f.metadata.get("internal"):
            continue
        s = schema_of(hints[f.name])
        if f.default is not dataclasses.MISSING:
            s["default"] = f.default
        elif f.default_factory is not dataclasses.MISSING:
            d = f.default_factory()
            s["default"] = dataclasses.asdict(d) if dataclasses.is_dataclass(d) else d
        else:
            required.append(f.name)
        props[f.name] = s
    out = {"type": "object", "additionalProperties": False, "properties": props}
    if cls.__doc__ and not cls.__doc__.startswith(cls.__name__ + "("):
        out["description"] = " ".join(cls.__doc__.split())
    if required:
        out["required"] = required
    return out
