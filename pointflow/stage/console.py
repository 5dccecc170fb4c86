"""The terminal a run is watched on: one live progress line (``pointflow run``, redrawn in
place) and log lines from every process of the run. Without care they overwrite each other
(a log line written into the middle of the progress line); here every log line on a terminal
first clears the line it starts on, so it replaces the progress line, which is redrawn under
it at the next update. Off a terminal nothing changes (no escape codes in files)."""
from __future__ import annotations

import logging
import sys
from typing import Optional, TextIO

#: Back to the start of the line and erase it (ANSI: carriage return, Erase in Line).
CLEAR_LINE = "\r\033[K"


def is_terminal(stream: Optional[TextIO]) -> bool:
    try:
        return bool(stream is not None and stream.isatty())
    except (AttributeError, ValueError, OSError):  # closed or not a real file
        return False


class _ClearingFormatter(logging.Formatter):
    """Starts each record with :data:`CLEAR_LINE` (the progress line it lands on is erased)."""

    def format(self, record: logging.LogRecord) -> str:
        return CLEAR_LINE + super().format(record)


def setup_logging(level: int, fmt: str, stream: Optional[TextIO] = None) -> None:
    """``logging.basicConfig`` on ``stream`` (stderr), with log lines that clear a progress
    line first when it is a terminal. A no-op when the root logger has handlers already."""
    stream = stream if stream is not None else sys.stderr
    handler = logging.StreamHandler(stream)
    handler.setFormatter(_ClearingFormatter(fmt) if is_terminal(stream) else logging.Formatter(fmt))
    logging.basicConfig(level=level, handlers=[handler])
