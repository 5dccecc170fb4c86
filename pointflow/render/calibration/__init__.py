"""Measured crossovers the render stage decides with, read from one place.

A calibration is a small JSON file named after what it measures (``crossover.json``: below
how many points the cpu tier beats the GPU tiers; ``raster_crossover.json``: where the wgpu
compute method beats quads). :func:`load` reads the user cache first
(``$XDG_CACHE_HOME/pointflow/<name>``, written by the bench command with ``--install``), then
the defaults shipped in this package (measured on the development machine, a 2-core VM with
Mesa lavapipe; ``bench/`` says how). Library code never reads ``bench/results/``, which a
wheel install does not have.
"""
from __future__ import annotations

import json
import os
from importlib import resources
from pathlib import Path
from typing import Any, Optional


def cache_dir() -> Path:
    """``$XDG_CACHE_HOME/pointflow`` (default ``~/.cache/pointflow``)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "pointflow"


def cache_path(name: str) -> Path:
    return cache_dir() / name


def _read(text: str, required: tuple[str, ...]) -> Optional[dict[str, Any]]:
    try:
        data = json.loads(text)
    except ValueError:
        return None
    if not isinstance(data, dict) or any(k not in data for k in required):
        return None
    return data


def load(name: str, required: tuple[str, ...]) -> tuple[Optional[dict[str, Any]], str]:
    """(data, where it came from): the user cache, then the shipped default; (None, why)
    when neither has a readable file with the ``required`` keys."""
    p = cache_path(name)
    try:
        data = _read(p.read_text(), required)
        if data is not None:
            return data, str(p)
    except OSError:
        pass
    try:
        ref = resources.files(__package__).joinpath(name)
        data = _read(ref.read_text(encoding="utf-8"), required)
        if data is not None:
            return data, f"shipped default {name}"
    except (OSError, FileNotFoundError):
        pass
    return None, "no calibration file"


def install(name: str, data: dict[str, Any]) -> Path:
    """Write a measurement to the user cache (what the bench commands' ``--install`` does)."""
    p = cache_path(name)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=2))
    tmp.replace(p)
    return p
