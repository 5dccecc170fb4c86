"""CURVE certificate files: ``pointflow keys NAME`` and loading them with clear errors.

A pair is ZeroMQ's own format (:func:`zmq.auth.create_certificates`): ``NAME.key`` holds
the public key (give it to the peer) and ``NAME.key_secret`` the public and the secret
key (keep it on this host, readable only by its owner).
"""
from __future__ import annotations

import os
from pathlib import Path

import zmq.auth

from ..errors import Error


class KeyFileError(Error, ValueError):
    """A key file is missing or does not hold what it should."""


def create_keypair(name: str, directory: str | os.PathLike = ".", overwrite: bool = False) -> tuple[Path, Path]:
    """Write ``NAME.key`` and ``NAME.key_secret`` into ``directory`` (secret: mode 0600)."""
    if not name or "/" in name or name.startswith("."):
        raise KeyFileError(f"key name must be a plain file name, got {name!r}")
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    pub, sec = d / f"{name}.key", d / f"{name}.key_secret"
    if not overwrite and (pub.exists() or sec.exists()):
        raise KeyFileError(f"{pub} or {sec} already exists; pick another name, remove them, or overwrite "
                           "them (pointflow keys --force; overwrite=True)")
    pub_s, sec_s = zmq.auth.create_certificates(str(d), name)
    os.chmod(sec_s, 0o600)
    return Path(pub_s), Path(sec_s)


def _load(path: str | os.PathLike) -> tuple[bytes, bytes | None]:
    p = Path(path)
    if not p.is_file():
        raise KeyFileError(f"key file {p} does not exist (create a pair with `pointflow keys NAME --dir DIR`)")
    try:
        public, secret = zmq.auth.load_certificate(str(p))
    except (OSError, ValueError) as exc:
        raise KeyFileError(f"{p} is not a ZeroMQ certificate file: {exc}") from None
    if not public or len(public) != 40:
        raise KeyFileError(f"{p} holds no valid public key")
    return public, secret


def load_secret(path: str | os.PathLike) -> tuple[bytes, bytes]:
    """(public, secret) from a ``NAME.key_secret`` file."""
    public, secret = _load(path)
    if not secret:
        raise KeyFileError(f"{path} holds no secret key (use the NAME.key_secret file, not NAME.key)")
    return public, secret


def load_public(path: str | os.PathLike) -> bytes:
    """The public key from a ``NAME.key`` (or ``NAME.key_secret``) file."""
    return _load(path)[0]


def authorized_keys(directory: str | os.PathLike) -> set[bytes]:
    """The public keys (Z85) of every ``*.key`` file in ``directory``."""
    d = Path(directory)
    if not d.is_dir():
        raise KeyFileError(f"authorized keys folder {d} does not exist")
    return {k for k, ok in zmq.auth.load_certificates(str(d)).items() if ok}
