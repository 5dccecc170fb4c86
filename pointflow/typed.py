"""The typed loader that config and every transport's options share: YAML-ish values →
dataclasses, with errors that name the key path (``render.size[0]``).

The bottom layer of configuration: it imports nothing of pointflow, so
:mod:`pointflow.config` and :mod:`pointflow.ingest.transports` can both import it and
imports run one way (config → transports → typed).
"""
from __future__ import annotations

import dataclasses
import difflib
import re
import types
import typing
from typing import Any, Literal, Optional, Union

from .errors import KeyedError


class ConfigError(KeyedError):
    """A configuration value is wrong; ``key`` (also ``path``) is the dotted key path."""

    @property
    def path(self) -> str:
        return self.key


class Constraint:
    """A bound on one option, declared once: called as ``fn(value, path)`` at load time it
    raises :class:`ConfigError`; :meth:`schema` gives the same bound as JSON-Schema keywords,
    so ``pointflow schema`` and ``pointflow validate`` cannot disagree. JSON-Schema bounds
    apply only to their own type (``minimum`` to numbers, ``minItems`` to arrays), so they sit
    beside an ``anyOf`` of an Optional or Union field without touching its other branches."""

    def __call__(self, v: Any, path: str) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def schema(self) -> dict:  # pragma: no cover - abstract
        raise NotImplementedError


class Bound(Constraint):
    """A number in a range; ``lo_open``/``hi_open`` exclude the end."""

    def __init__(self, lo: Optional[float] = None, hi: Optional[float] = None, *,
                 lo_open: bool = False, hi_open: bool = False, note: str = ""):
        self.lo, self.hi, self.lo_open, self.hi_open, self.note = lo, hi, lo_open, hi_open, note

    def ok(self, v) -> bool:
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            return False
        if self.hi is not None and (v >= self.hi if self.hi_open else v > self.hi):
            return False
        return True

    def describe(self) -> str:
        lo, hi = self.lo, self.hi
        if lo is not None and hi is not None:
            if self.lo_open or self.hi_open:
                return f"must be in {'(' if self.lo_open else '['}{lo}, {hi}{')' if self.hi_open else ']'}"
            return f"must be in {lo}..{hi}"
        if lo is not None:
            return f"must be {'>' if self.lo_open else '>='} {lo}"
        return f"must be {'<' if self.hi_open else '<='} {hi}"

    def __call__(self, v, path):
        if isinstance(v, (int, float)) and not isinstance(v, bool) and not self.ok(v):
            raise ConfigError(path, f"{self.describe()}{f' ({self.note})' if self.note else ''}, got {v!r}")

    def schema(self) -> dict:
        s: dict = {}
        if self.lo is not None:
            s["exclusiveMinimum" if self.lo_open else "minimum"] = self.lo
        if self.hi is not None:
            s["exclusiveMaximum" if self.hi_open else "maximum"] = self.hi
        return s


class Length(Constraint):
    """A list of ``lo``..``hi`` items."""

    def __init__(self, lo: int, hi: Optional[int] = None):
        self.lo, self.hi = lo, lo if hi is None else hi

    def __call__(self, v, path):
        if isinstance(v, list) and not self.lo <= len(v) <= self.hi:
            want = str(self.lo) if self.lo == self.hi else f"{self.lo} to {self.hi}"
            raise ConfigError(path, f"must have {want} items, got {len(v)}: {v!r}")

    def schema(self) -> dict:
        return {"minItems": self.lo, "maxItems": self.hi}


class Each(Constraint):
    """Every item of a list meets ``inner``."""

    def __init__(self, inner: Constraint):
        self.inner = inner

    def __call__(self, v, path):
        if isinstance(v, list):
            for i, item in enumerate(v):
                self.inner(item, f"{path}[{i}]")

    def schema(self) -> dict:
        return {"items": self.inner.schema()}


class Prefix(Constraint):
    """A string that starts with one of ``prefixes`` (a URL scheme)."""

    def __init__(self, prefixes: tuple[str, ...], what: str):
        self.prefixes, self.what = tuple(prefixes), what

    def __call__(self, v, path):
        if isinstance(v, str) and not v.startswith(self.prefixes):
            raise ConfigError(path, f"must be {self.what}, got {v!r}")

    def schema(self) -> dict:
        return {"pattern": "^(" + "|".join(re.escape(p) for p in self.prefixes) + ")"}


class AllOf(Constraint):
    """Several constraints on one option; ``message`` (when given) replaces their own, so a
    field keeps one sentence such as "must be [width, height] with each in 1..16384"."""

    def __init__(self, parts: tuple[Constraint, ...], message: str = ""):
        self.parts, self.message = tuple(parts), message

    def __call__(self, v, path):
        for c in self.parts:
            try:
                c(v, path)
            except ConfigError:
                if not self.message:
                    raise
                raise ConfigError(path, f"{self.message}, got {v!r}") from None

    def schema(self) -> dict:
        out: dict = {}
        for c in self.parts:
            out.update(c.schema())
        return out


#: The shared bounds: use them as ``field(default=..., metadata=check(positive))``.
positive = Bound(0, lo_open=True)
non_negative = Bound(0)
at_least_one = Bound(1)
endpoint = Prefix(("ipc://", "tcp://", "inproc://"), "a ZeroMQ endpoint (ipc://, tcp://)")


def check(*constraints: Any, message: str = "") -> dict:
    """Field metadata: the option's bounds, checked at load (not for null) and written into
    the JSON Schema. Give :class:`Constraint` objects (``positive``, ``Bound(1, 16384)``,
    ``Length(2)``...); a plain ``fn(value, path)`` still validates but cannot reach the
    schema, and tests/spine/config/test_schema_bounds.py fails on one in the pipeline config."""
    if len(constraints) == 1 and not message:
        return {"check": constraints[0]}
    return {"check": AllOf(constraints, message)}


def constraint_schema(fn: Any) -> dict:
    """The JSON-Schema keywords of a field's ``check`` ({} for a plain function)."""
    return fn.schema() if isinstance(fn, Constraint) else {}


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


def _yaml_number_hint(value: Any) -> str:
    """YAML (1.1, PyYAML) reads 1.5e6 and 1e-3 as strings (its floats need a dot and a signed
    exponent): say how to write them as numbers."""
    if not isinstance(value, str):
        return ""
    try:
        x = float(value)
    except ValueError:
        return ""
    if x != x or x in (float("inf"), float("-inf")):
        return ""
    plain = str(int(x)) if x.is_integer() and abs(x) < 1e16 else repr(x)
    return f" (YAML reads {value} as text; write {plain})"


def convert(value: Any, tp: Any, path: str) -> Any:
    origin = typing.get_origin(tp)
    if tp is Any:
        return value
    if origin in (Union, types.UnionType):
        alts = typing.get_args(tp)
        errors = []
        for alt in alts:
            try:
                return convert(value, alt, path)
            except ConfigError as exc:
                errors.append(exc)
        # The value was clearly meant for one alternative (a mapping for the only dataclass,
        # anything but null for the only non-null type): its own error names the key inside.
        meant = [i for i, a in enumerate(alts) if dataclasses.is_dataclass(a)] if isinstance(value, dict) else []
        if len(meant) != 1 and value is not None:
            meant = [i for i, a in enumerate(alts) if a is not type(None)]
        if len(meant) == 1:
            raise errors[meant[0]]
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
        if isinstance(value, float) and value.is_integer() and abs(value) < 2 ** 63:
            return int(value)  # 1.5e+6 (YAML's float) is a whole number
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(path, f"expected an integer, got {type(value).__name__} {value!r}{_yaml_number_hint(value)}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(path, f"expected a number, got {type(value).__name__} {value!r}{_yaml_number_hint(value)}")
        if value != value or value in (float("inf"), float("-inf")):
            raise ConfigError(path, f"must be finite, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(path, f"expected a string, got {type(value).__name__} {value!r}")
        return value
    raise ConfigError(path, f"unsupported type {tp!r}")  # pragma: no cover


def load_dataclass(cls, data: Any, path: str):
    if isinstance(data, bool) and _switchable(cls):  # ``edl: true`` for ``edl: {enabled: true}``
        data = {"enabled": data}
    if not isinstance(data, dict):
        raise ConfigError(path, f"expected a mapping, got {type(data).__name__} {data!r}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if not f.metadata.get("internal")}
    check_keys(data, list(fields), path)
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


def _switchable(cls) -> bool:
    """A section with an ``enabled`` switch: ``true``/``false`` stand for ``{enabled: ...}``."""
    return any(f.name == "enabled" for f in dataclasses.fields(cls))


def check_keys(data: dict, valid: list[str], path: str) -> None:
    """Refuse the first key not in ``valid``, naming it, the closest valid key and all of them."""
    unknown = [k for k in data if k not in valid]
    if unknown:
        key = str(unknown[0])
        near = difflib.get_close_matches(key, valid, n=1, cutoff=0.75)
        if not near and len(key) >= 4:  # a part of the name: map.budget -> point_budget
            near = [v for v in valid if key.lower() in v.lower().split("_") or v.lower().endswith("_" + key.lower())][:1]
        hint = f" (did you mean {near[0]!r}?)" if near else ""
        raise ConfigError(join_path(path, key), f"unknown key {key!r}{hint}; " +
                          (f"expected one of {', '.join(valid)}" if valid else f"{path or 'this block'} takes no keys"))


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
        if _switchable(tp):
            return {"anyOf": [{"type": "boolean", "description": "shorthand for {enabled: true|false}"},
                              dataclass_schema(tp)]}
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
        extra = constraint_schema(f.metadata.get("check"))
        if isinstance(s.get("items"), dict) and isinstance(extra.get("items"), dict):  # Each(...): keep the item type
            extra = {**extra, "items": {**s["items"], **extra["items"]}}
        s.update(extra)
        if f.default is not dataclasses.MISSING:
            s["default"] = f.default
        elif f.default_factory is not dataclasses.MISSING:
            d = f.default_factory()
            s["default"] = dataclasses.asdict(d) if dataclasses.is_dataclass(d) else d
        else:
            required.append(f.name)
        props[f.name] = s
    out = {"type": "object", "additionalProperties": False, "properties": props}
    out.update(getattr(cls, "json_schema_extra", {}))  # what relates two options, said in JSON Schema
    if cls.__doc__ and not cls.__doc__.startswith(cls.__name__ + "("):
        out["description"] = " ".join(cls.__doc__.split())
    if required:
        out["required"] = required
    return out
