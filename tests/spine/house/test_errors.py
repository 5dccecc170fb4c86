"""One error root (issue 38): every error class of the package is a pointflow.Error, the
errors users catch are exported from ``pointflow``, and a keyed error crosses a process
boundary as fields (key, message), never as text to be sliced."""
from __future__ import annotations

import importlib
import inspect
import os
import pickle
import pkgutil

import pytest

import pointflow
from pointflow import Pipeline
from pointflow.errors import Error, from_fields, to_fields

from .. import probe_stage
from ..helpers import small_config


def _modules():
    """Every module of the package that imports here (some need optional libraries)."""
    for info in pkgutil.walk_packages(pointflow.__path__, "pointflow."):
        if info.name.endswith("__main__"):
            continue
        try:
            yield importlib.import_module(info.name)
        except ImportError:
            continue


def test_every_error_class_is_a_pointflow_error():
    found, bad = [], []
    for mod in _modules():
        for name, obj in vars(mod).items():
            if inspect.isclass(obj) and issubclass(obj, BaseException) and obj.__module__ == mod.__name__:
                found.append(f"{mod.__name__}.{name}")
                if not issubclass(obj, Error):
                    bad.append(f"{mod.__name__}.{name}")
    assert len(found) >= 20, found  # the walk saw the package's errors
    assert not bad, bad


def test_the_errors_users_catch_are_exported():
    for name in ("Error", "KeyedError", "ConfigError", "PipelineFailed", "ControlError", "PlaybackError",
                 "LinkRefused", "SendError", "ChunkError", "FormatError", "MapError"):
        assert name in pointflow.__all__, name
        cls = getattr(pointflow, name)
        assert issubclass(cls, pointflow.Error), name
    # builtin bases kept: callers catching ValueError still catch bad input
    for name in ("ConfigError", "ControlError", "PlaybackError", "SendError", "ChunkError", "FormatError"):
        assert issubclass(getattr(pointflow, name), ValueError), name
    assert issubclass(pointflow.PipelineFailed, RuntimeError)
    assert issubclass(pointflow.LinkRefused, ConnectionRefusedError)


@pytest.mark.parametrize("name", ["ConfigError", "ControlError", "PlaybackError", "FormatError", "MapError"])
def test_a_keyed_error_keeps_its_fields_across_pickle_and_fields(name):
    cls = getattr(pointflow, name)
    exc = cls("render.size[0]", "must be > 0: got -1")
    assert (exc.key, exc.message) == ("render.size[0]", "must be > 0: got -1")
    assert str(exc) == "render.size[0]: must be > 0: got -1"
    back = pickle.loads(pickle.dumps(exc))
    assert type(back) is cls and (back.key, back.message) == (exc.key, exc.message)
    rebuilt = from_fields(to_fields(exc))
    assert type(rebuilt) is cls and (rebuilt.key, rebuilt.message) == (exc.key, exc.message)
    assert from_fields(to_fields(RuntimeError("no key"))) is None


def test_a_config_error_in_a_stage_arrives_with_its_key(tmp_path, monkeypatch):
    """A ConfigError raised in a stage process reaches the parent as PipelineFailed whose
    ``cause`` is a ConfigError with the same key and message (sent as fields)."""
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(p for p in (probe_stage.import_root(),
                                                                 os.environ.get("PYTHONPATH")) if p))
    from pointflow.stage.kinds import register_stage_kind, unregister_stage_kind

    register_stage_kind(probe_stage.KEYED)
    try:
        pipe = Pipeline.from_dict(small_config(), out_dir=str(tmp_path))
        with pytest.raises(pointflow.PipelineFailed) as info:
            with pipe:
                pipe.wait(120)
    finally:
        unregister_stage_kind(probe_stage.KEYED.name)
    cause = info.value.cause
    assert isinstance(cause, pointflow.ConfigError), (info.value, cause)
    assert (cause.key, cause.message) == ("probe.option", "refused by the probe stage")
    assert isinstance(info.value, pointflow.Error)
