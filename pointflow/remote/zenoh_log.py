"""Zenoh's own log lines, read back into this process: refused connections counted and
logged through :mod:`logging`, not lost on stdout.

The Zenoh engine (Rust) reports a refused TLS handshake only in its log ("invalid peer
certificate: UnknownIssuer" on the end that refuses); its Python API has events for
transports that opened or closed, none for one that never opened. So the process that
wants to know (``pointflow router``) sends the engine's log, which it writes to file
descriptor 1, into a pipe, and a thread here parses each line: warnings and errors go to
the Python log of the stage (with the supervisor's format and its stderr), and the ones
that say a link was refused are counted by reason. Level: ``RUST_LOG`` when set, else
``warn``.
"""
from __future__ import annotations

import collections
import logging
import os
import re
import threading
from typing import Optional

#: ANSI colour sequences the engine's log writer puts around level and target.
_ANSI = re.compile(r"\x1b\[[0-9;]*m")
#: ``2026-11-23T22:55:53.410763Z  WARN acc-0 ThreadId(05) zenoh_link_tls::unicast: message``
_LINE = re.compile(r"^\S+\s+(?P<level>TRACE|DEBUG|INFO|WARN|ERROR)\s+(?:.*?\s)?(?P<target>zenoh[\w:]*|\w+(?:::\w+)+):\s"
                   r"(?P<msg>.*)$")
#: Link layers whose warnings on an accepting thread are refused connections.
_SECURE_LINKS = ("zenoh_link_tls", "zenoh_link_quic")
#: What the engine appends to some warnings; no help to a user of pointflow.
_NOISE = (" Hint: increase the system open file limit.",)

_LEVELS = {"TRACE": logging.DEBUG, "DEBUG": logging.DEBUG, "INFO": logging.INFO, "WARN": logging.WARNING,
           "ERROR": logging.ERROR}


def refusal_reason(target: str, msg: str) -> Optional[str]:
    """A short reason when a log line says a TLS/QUIC link was refused, else None."""
    if not target.startswith(_SECURE_LINKS):
        return None
    m = msg.lower()
    if any(w in m for w in ("certificate", "alert", "handshake", "tls", "peer")):
        # "invalid peer certificate: UnknownIssuer. Hint: ..." -> "invalid peer certificate: UnknownIssuer"
        return msg.split(" at /", 1)[0].split(". ", 1)[0].strip(" .")[:120]
    return None


class EngineLog:
    """Reads the engine's log from fd 1 (see the module doc); :attr:`refused` counts refused
    links by reason, :attr:`last_refusal` is the newest line that said so."""

    def __init__(self, log: logging.Logger, default_level: str = "warn"):
        self.log = log
        self.refused: collections.Counter[str] = collections.Counter()
        self.last_refusal = ""
        self.lines = 0
        self._lock = threading.Lock()
        self._level = default_level
        self._thread: Optional[threading.Thread] = None

    def start(self) -> None:
        """Send fd 1 into a pipe read here, then turn the engine's log on (once per process)."""
        import zenoh

        r, w = os.pipe()
        os.dup2(w, 1)
        os.close(w)
        self._thread = threading.Thread(target=self._read, args=(r,), name="pointflow-zenoh-log", daemon=True)
        self._thread.start()
        zenoh.init_log_from_env_or(self._level)

    def _read(self, fd: int) -> None:
        with os.fdopen(fd, "r", encoding="utf-8", errors="replace") as f:
            for raw in f:
                self.feed(raw)

    def feed(self, raw: str) -> None:
        """Handle one line of the engine's log."""
        line = _ANSI.sub("", raw).rstrip()
        if not line:
            return
        self.lines += 1
        m = _LINE.match(line)
        if not m:
            self.log.info("zenoh: %s", line)
            return
        level, target, msg = m["level"], m["target"], m["msg"]
        for n in _NOISE:
            msg = msg.replace(n, "")
        reason = refusal_reason(target, msg) if level in ("WARN", "ERROR") else None
        if reason:
            with self._lock:
                self.refused[reason] += 1
                self.last_refusal = msg.split(" at /", 1)[0].strip(" .")
            self.log.warning("refused a connection (%s): %s", target, self.last_refusal)
            return
        self.log.log(_LEVELS[level], "zenoh %s: %s", target, re.sub(r"\s+at /\S+\.rs:\d+\.?", "", msg))

    def counts(self) -> dict[str, int]:
        with self._lock:
            return dict(self.refused)
