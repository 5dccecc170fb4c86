"""Choosing a render tier, and falling back when one fails.

Modelled on pyzmq's backend selection: an environment override, candidates tried in
order, every skip explained, and a clear error quoting the first real failure when
nothing works.

- ``POINTFLOW_BACKEND`` (``auto``/``wgpu``/``gl``/``cpu``) overrides ``render.backend``.
- An explicit tier is strict: it is the only candidate (its failure is the error).
- ``auto`` tries wgpu → gl → cpu. Scenes smaller than the cpu crossover go to the cpu
  tier first: below it, uploading to a GPU costs more than it saves (measured by
  ``bench/bench_tiers.py``, see :func:`crossover_points` for where the number comes from).
- :func:`fallback_after` gives the next tier when one raises ``RenderError`` mid-run.
"""
from __future__ import annotations

import importlib
import json
import logging
import os
from pathlib import Path
from typing import Callable, Optional

from ..config import RenderConfig
from . import calibration
from .base import Renderer, RenderError

log = logging.getLogger("pointflow.render.select")

#: Tiers in order of preference for ``auto``.
ORDER = ("wgpu", "gl", "cpu")
#: Where each tier's class lives (imported lazily: a missing GPU stack is a skip, not a crash).
TIERS = {
    "wgpu": "pointflow.render.wgpu_tier:WgpuRenderer",
    "gl": "pointflow.render.gl:GlRenderer",
    "cpu": "pointflow.render.cpu:CpuRenderer",
}
ENV_BACKEND = "POINTFLOW_BACKEND"
ENV_CROSSOVER = "POINTFLOW_CROSSOVER"
#: Used when no calibration file is readable (the package ships one, see
#: :mod:`pointflow.render.calibration`). ``bench/bench_tiers.py`` measured 0 on the
#: development machine (2 cores, lavapipe/llvmpipe): the GPU tiers beat the numpy tier even
#: at 1,000 points there (its fixed per-frame cost is ~12 ms at 1280x720), so size alone
#: never sends a scene to the cpu tier unless a measurement says so.
DEFAULT_CROSSOVER = 0
CROSSOVER_FILE = "crossover.json"


def _load_class(tier: str) -> type[Renderer]:
    mod, _, name = TIERS[tier].partition(":")
    return getattr(importlib.import_module(mod), name)


def cache_path() -> Path:
    """The per-user file the benchmark writes the measured crossover to."""
    return calibration.cache_path(CROSSOVER_FILE)


def _read_crossover_file(path: Path) -> Optional[int]:
    try:
        data = json.loads(path.read_text())
        return int(data["crossover_points"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def crossover_points(cfg: Optional[RenderConfig] = None) -> tuple[int, str]:
    """(points, where it came from). First match wins: ``render.cpu_crossover_points``
    (an int), env ``POINTFLOW_CROSSOVER`` (an int or a JSON file path), the user cache
    file (:func:`cache_path`), the default shipped in the package (see
    :mod:`pointflow.render.calibration`), then :data:`DEFAULT_CROSSOVER`."""
    if cfg is not None and isinstance(cfg.cpu_crossover_points, int):
        return cfg.cpu_crossover_points, "render.cpu_crossover_points"
    env = os.environ.get(ENV_CROSSOVER, "").strip()
    if env:
        if env.isdigit():
            return int(env), f"${ENV_CROSSOVER}"
        v = _read_crossover_file(Path(env))
        if v is not None:
            return v, f"${ENV_CROSSOVER} ({env})"
        log.warning("%s=%r is neither an integer nor a readable crossover JSON; ignored", ENV_CROSSOVER, env)
    data, where = calibration.load(CROSSOVER_FILE, ("crossover_points",))
    try:
        return int(data["crossover_points"]), where  # type: ignore[index]
    except (TypeError, ValueError):
        return DEFAULT_CROSSOVER, "built-in default"


def _candidates(cfg: RenderConfig, expected_points: Optional[int], capacity: int, lines: list[str]) -> list[str]:
    env = os.environ.get(ENV_BACKEND, "").strip().lower()
    backend = cfg.backend
    if env:
        if env not in ("auto",) + ORDER:
            raise RenderError(f"${ENV_BACKEND}={env!r}: expected one of auto, {', '.join(ORDER)}")
        lines.append(f"${ENV_BACKEND}={env} overrides render.backend={backend}")
        backend = env
    if backend != "auto":
        lines.append(f"backend {backend} requested explicitly: no other tier is tried")
        return [backend]
    n = capacity if expected_points is None else int(expected_points)
    xo, src = crossover_points(cfg)
    if n < xo:
        lines.append(f"cpu first: scene of {n} points < crossover {xo} (from {src}); a GPU upload costs more than it saves")
        return ["cpu", "wgpu", "gl"]
    lines.append(f"scene of {n} points >= crossover {xo} (from {src}): GPU tiers first")
    return list(ORDER)


def _describe(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}".strip().rstrip(":")


def _try(tiers: list[str], cfg: RenderConfig, capacity: int, channels: list[str], lines: list[str],
         make: Optional[Callable[[str], type[Renderer]]] = None) -> Renderer:
    first: Optional[tuple[str, BaseException]] = None
    for tier in tiers:
        try:
            cls = (make or _load_class)(tier)
        except (ImportError, AttributeError) as exc:
            lines.append(f"{tier}: skipped: not available ({_describe(exc)})")
            continue
        try:
            r = cls(cfg, capacity, channels)
        except Exception as exc:  # noqa: BLE001 - any start-up failure is a reason to skip
            lines.append(f"{tier}: skipped: {_describe(exc)}")
            first = first or (tier, exc)
            continue
        lines.append(f"{tier}: chosen")
        if getattr(r, "raster", None):  # the wgpu tier's raster method and why (render.raster)
            lines.append(f"{tier}: raster method {r.raster} ({getattr(r, '_raster_why', '')})")
        for line in lines:
            log.info("tier selection: %s", line)
        return r
    for line in lines:
        log.info("tier selection: %s", line)
    detail = f"; first error ({first[0]}): {_describe(first[1])}" if first else ""
    err = RenderError(f"no render tier could start (tried {', '.join(tiers)}){detail}")
    err.reasons = list(lines)  # type: ignore[attr-defined]
    raise err from (first[1] if first else None)


def select_renderer(cfg: RenderConfig, capacity: int, channels: list[str], *,
                    expected_points: Optional[int] = None) -> tuple[Renderer, list[str]]:
    """Start the best tier for this config; returns (renderer, log lines saying why each
    candidate was skipped or chosen). ``expected_points`` (default: ``capacity``) is
    compared with the crossover. Raises RenderError when no tier starts."""
    lines: list[str] = []
    tiers = _candidates(cfg, expected_points, capacity, lines)
    r = _try(tiers, cfg, capacity, channels, lines)
    r.selection_log = list(lines)  # type: ignore[attr-defined]
    return r, lines


def next_tiers(tier: str) -> list[str]:
    """Tiers after ``tier`` in fallback order (wgpu → gl → cpu)."""
    return list(ORDER[ORDER.index(tier) + 1:]) if tier in ORDER else ["cpu"]


def fallback_after(renderer: Renderer, exc: BaseException, cfg: Optional[RenderConfig] = None,
                   capacity: Optional[int] = None, channels: Optional[list[str]] = None) -> Renderer:
    """The next working tier after ``renderer`` failed with ``exc`` (device lost, pipeline
    error). The failed renderer is closed; the reasons are logged and kept on the new
    renderer's ``selection_log``. Raises RenderError when no later tier starts (the cpu
    tier has nothing after it)."""
    cfg = cfg or renderer.cfg
    capacity = renderer.capacity if capacity is None else capacity
    channels = renderer.channels if channels is None else channels
    lines = [f"{renderer.tier}: failed mid-run ({_describe(exc)}); falling back"]
    try:
        renderer.close()
    except Exception as cexc:  # noqa: BLE001 - a lost device may not close cleanly
        lines.append(f"{renderer.tier}: close failed ({_describe(cexc)})")
    tiers = next_tiers(renderer.tier)
    if not tiers:
        for line in lines:
            log.error("tier fallback: %s", line)
        raise RenderError(f"{renderer.tier} tier failed and no tier is left after it: {_describe(exc)}") from exc
    r = _try(tiers, cfg, capacity, channels, lines)
    r.selection_log = list(lines)  # type: ignore[attr-defined]
    return r
