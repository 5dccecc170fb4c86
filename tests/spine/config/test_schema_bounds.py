"""`pointflow schema` rejects exactly what `pointflow validate` rejects, over the bounds of
every option. The cases are generated from the config dataclasses' own ``check(...)``
constraints (and Literal choices), so a block added later is covered without editing this
file; a bound written as a plain function (which the schema cannot carry) fails here."""
from __future__ import annotations

import copy
import dataclasses
import types
import typing
from typing import Any, Literal, Optional, Union  # Optional: NewBlock's hints resolve here

import jsonschema
import pytest

from pointflow.config import ConfigError, PipelineConfig, json_schema, load_config
from pointflow.typed import Constraint

BASE = {"source": {"transport": "synthetic"}}


def _unwrap(tp) -> list:
    if typing.get_origin(tp) in (Union, types.UnionType):
        return [a for a in typing.get_args(tp) if a is not type(None)]
    return [tp]


def walk(cls, path=()):
    """(path, field, type) of every option of the pipeline config, nested blocks included."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if f.metadata.get("internal"):
            continue
        p = path + (f.name,)
        yield p, f, hints[f.name]
        for alt in _unwrap(hints[f.name]):
            if dataclasses.is_dataclass(alt):
                yield from walk(alt, p)


OPTIONS = list(walk(PipelineConfig))


def _default(f):
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None


def _probes(keywords: dict, is_int: bool) -> list:
    """Numbers either side of and on each bound."""
    step = 1 if is_int else 0.5
    out = []
    for k in ("minimum", "exclusiveMinimum", "maximum", "exclusiveMaximum"):
        if k in keywords:
            b = keywords[k]
            out += [b - step, b, b + step]
    return out


def _cases(f, tp) -> list:
    """Values for one option, near every bound its constraint declares."""
    fn = f.metadata.get("check")
    kw = fn.schema() if isinstance(fn, Constraint) else {}
    alts = _unwrap(tp)
    values: list = []
    for alt in alts:
        if typing.get_origin(alt) is Literal:
            values += list(typing.get_args(alt)) + ["no-such-choice"]
    nums = [a for a in alts if a in (int, float)]
    if nums:
        values += _probes(kw, nums[0] is int)
    lists = [a for a in alts if typing.get_origin(a) is list]
    if lists:
        item_int = typing.get_args(lists[0])[0] is int
        d = _default(f)
        lo, hi = kw.get("minItems", 1), kw.get("maxItems", 3)
        # the default extended by its last item, or ascending numbers (color_range wants lo < hi)
        make = (lambda n: [d[min(i, len(d) - 1)] for i in range(n)]) if isinstance(d, list) and d \
            else (lambda n: [(i if item_int else float(i)) for i in range(n)])
        for n in sorted({lo - 1, lo, hi, hi + 1} - {-1}):
            values.append(make(n))
        base = make(max(lo, 1))
        for v in _probes(kw.get("items", {}), item_int):
            values.append([v] + list(base[1:]))
    if "pattern" in kw:
        values += ["http://example.invalid", "ipc:///tmp/pointflow-schema-case.sock"]
    return values


def _set(path, value) -> dict:
    d = copy.deepcopy(BASE)
    cur = d
    for k in path[:-1]:
        cur = cur.setdefault(k, {})
    cur[path[-1]] = value
    return d


CASES = [(".".join(p), p, v) for p, f, tp in OPTIONS for v in _cases(f, tp)]
SCHEMA = json_schema()


def test_every_bound_is_declarative():
    """A plain-function check validates but never reaches the schema: use Constraint objects
    (positive, non_negative, at_least_one, Bound, Length, Each, Prefix) instead."""
    plain = [".".join(p) for p, f, _ in OPTIONS
             if f.metadata.get("check") is not None and not isinstance(f.metadata["check"], Constraint)]
    assert not plain, f"bounds the JSON Schema cannot carry: {plain}"


def test_cases_cover_the_bounded_options():
    bounded = {".".join(p) for p, f, _ in OPTIONS if f.metadata.get("check") is not None}
    probed = {name for name, _, _ in CASES}
    assert bounded <= probed, bounded - probed
    # the options issue 22 listed are among them
    for name in ("ring.max_points", "render.size", "cadence.target_hz", "render.pick_radius",
                 "render.output.keep_last", "send.quantise", "send.send_hwm"):
        assert name in bounded, name


@pytest.mark.parametrize("name,path,value", CASES, ids=[f"{n}={v!r}" for n, _, v in CASES])
def test_schema_rejects_what_validate_rejects(name, path, value):
    data = _set(path, value)
    try:
        load_config(copy.deepcopy(data))
        validate_ok, why = True, ""
    except ConfigError as exc:
        validate_ok, why = False, str(exc)
    errors = [e.message for e in jsonschema.Draft202012Validator(SCHEMA).iter_errors(data)]
    assert validate_ok == (not errors), (
        f"{name}={value!r}: validate {'accepts' if validate_ok else 'rejects (' + why + ')'}, "
        f"schema {'accepts' if not errors else 'rejects (' + '; '.join(errors) + ')'}")


@pytest.mark.parametrize("name,value", [
    ("ring.max_points", 0), ("render.size", [0, 720]), ("render.size", [1280]),
    ("render.size", [20000, 720]), ("cadence.target_hz", 0), ("render.pick_radius", -3),
    ("render.output.keep_last", -1), ("send.quantise", -1),
])
def test_the_issues_examples_are_refused_by_both(name, value):
    data = _set(tuple(name.split(".")), value)
    with pytest.raises(ConfigError):
        load_config(copy.deepcopy(data))
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(data, SCHEMA)


def test_a_new_block_using_the_shared_checks_gets_schema_bounds():
    """What another block gets by writing ``field(default=..., metadata=check(positive))``."""
    from dataclasses import dataclass, field

    from pointflow.typed import Length, at_least_one, check, dataclass_schema, load_dataclass, non_negative, positive

    @dataclass
    class NewBlock:
        rate_hz: float = field(default=1.0, metadata=check(positive))
        keep: int = field(default=0, metadata=check(non_negative))
        cap: Optional[int] = field(default=None, metadata=check(at_least_one))
        pair: list[float] = field(default_factory=lambda: [0.0, 1.0], metadata=check(Length(2)))

    props = dataclass_schema(NewBlock)["properties"]
    assert props["rate_hz"]["exclusiveMinimum"] == 0 and props["keep"]["minimum"] == 0
    assert props["cap"]["minimum"] == 1 and props["pair"]["minItems"] == props["pair"]["maxItems"] == 2
    schema = dataclass_schema(NewBlock)
    for bad in ({"rate_hz": 0}, {"keep": -1}, {"cap": 0}, {"pair": [1.0]}, {"rat_hz": 2}):
        with pytest.raises(ConfigError):
            load_dataclass(NewBlock, bad, "new")
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(bad, schema)
    for ok in ({"rate_hz": 0.5}, {"keep": 0}, {"cap": None}, {"cap": 1}, {"pair": [2.0, 3.0]}):
        load_dataclass(NewBlock, ok, "new")
        jsonschema.validate(ok, schema)
