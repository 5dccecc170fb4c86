"""The root of pointflow's errors, and the keyed family: one ``except pointflow.Error``
catches every error the package raises on purpose.

Most refusals name *where* (a config key path, a file, an argument) and *what*: they are
:class:`KeyedError`, with both as fields, so an error that crosses a process boundary (a
reply on a socket, a stage's report to the supervisor) travels as :func:`to_fields` and
is rebuilt with :func:`from_fields`, never by slicing its text. Every error class keeps
its builtin base too (``ValueError`` for bad input), so ``except ValueError`` still works.

At the bottom of the package: imports nothing of pointflow.
"""
from __future__ import annotations

from typing import Any, Optional


class Error(Exception):
    """Root of every error pointflow raises on purpose."""


#: Keyed error classes by name, for :func:`from_fields` (each subclass adds itself).
_KEYED: dict[str, type["KeyedError"]] = {}


class KeyedError(Error, ValueError):
    """A refusal naming where (``key``: a dotted key path, a file, an argument; may be
    empty) and what (``message``); ``str()`` is ``"key: message"``."""

    def __init__(self, key: str, message: str):
        self.key = key
        self.message = message
        super().__init__(self._text(key, message))

    @staticmethod
    def _text(key: str, message: str) -> str:
        return f"{key}: {message}" if key else message

    def __reduce__(self):  # picklable with its fields (the default would pass the text as key)
        return (type(self), (self.key, self.message))

    def __init_subclass__(cls, **kw: Any) -> None:
        super().__init_subclass__(**kw)
        _KEYED.setdefault(cls.__name__, cls)


_KEYED["KeyedError"] = KeyedError


def to_fields(exc: BaseException) -> dict[str, Any]:
    """What crosses a process boundary for ``exc``: ``{"class", "key", "message"}`` for a
    :class:`KeyedError`, ``{"class", "message"}`` otherwise."""
    if isinstance(exc, KeyedError):
        return {"class": type(exc).__name__, "key": exc.key, "message": exc.message}
    return {"class": type(exc).__name__, "message": str(exc)}


def from_fields(fields: Optional[dict], default: type[KeyedError] = KeyedError) -> Optional[KeyedError]:
    """The keyed error :func:`to_fields` described (its class when it is a known keyed
    error, else ``default``); None when ``fields`` holds no key."""
    if not isinstance(fields, dict) or not isinstance(fields.get("key"), str):
        return None
    cls = _KEYED.get(str(fields.get("class")), default)
    if not issubclass(cls, default):
        cls = default
    return cls(fields["key"], str(fields.get("message", "")))


__all__ = ["Error", "KeyedError", "to_fields", "from_fields"]
