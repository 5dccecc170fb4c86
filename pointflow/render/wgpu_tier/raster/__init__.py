"""Raster methods of the wgpu tier behind one interface (:class:`.base.RasterMethod`), and
how ``render.raster`` picks one.

``auto`` uses the compute method for screen-size points up to a measured size and from a
measured ring size per target pixel on (its per-pixel resolve is a fixed cost); the numbers
come from :mod:`pointflow.render.calibration` (``raster_crossover.json``, written by
``bench/bench_render.py --raster-crossover --install``).
"""
from __future__ import annotations

import os
from typing import Any

from ... import calibration
from .base import FramePlan, Gpu, RasterMethod
from .compute import KEY64_FEATURES, ComputeRaster
from .quads import QuadsRaster

#: ``render.raster`` value -> method
METHODS: dict[str, type[RasterMethod]] = {"quads": QuadsRaster, "compute": ComputeRaster}
#: used when no calibration file is readable
DEFAULT_MAX_COMPUTE_PX = 8.0
DEFAULT_MIN_POINTS_PER_PIXEL = 0.02
ENV_RASTER = "POINTFLOW_RASTER"
CALIBRATION_FILE = "raster_crossover.json"

__all__ = ["METHODS", "RasterMethod", "Gpu", "FramePlan", "choose_raster", "crossover", "KEY64_FEATURES"]


def crossover() -> tuple[float, float, str]:
    """(largest screen point size in px at which compute measured faster than quads, smallest
    ring capacity per target pixel from which it did, where the numbers come from)."""
    data, where = calibration.load(CALIBRATION_FILE, ("max_compute_point_px", "min_compute_points_per_pixel"))
    try:
        return float(data["max_compute_point_px"]), float(data["min_compute_points_per_pixel"]), where  # type: ignore[index]
    except (TypeError, ValueError):
        return DEFAULT_MAX_COMPUTE_PX, DEFAULT_MIN_POINTS_PER_PIXEL, "built-in default"


def choose_raster(cfg: Any, features: Any, key_bytes_needed: int, max_binding: int,
                  capacity: int = 0) -> tuple[str, str]:
    """("compute" | "quads", why) for ``render.raster`` (or env ``POINTFLOW_RASTER``)."""
    want = os.environ.get(ENV_RASTER, "").strip().lower() or cfg.raster
    src = f"${ENV_RASTER}={want}" if os.environ.get(ENV_RASTER, "").strip() else f"render.raster={want}"
    if want not in ("auto", "compute", "quads"):
        raise ValueError(f"{src}: expected auto, compute or quads")
    fits = key_bytes_needed <= max_binding
    if want == "quads":
        return "quads", f"{src}"
    if want == "compute":
        if not fits:
            raise ValueError(f"{src}: the per-pixel key buffer needs {key_bytes_needed} bytes, "
                             f"the device allows {max_binding} per storage buffer (render.size too large)")
        return "compute", src
    if not fits:
        return "quads", f"{src}: key buffer of {key_bytes_needed} bytes > device limit {max_binding}: quads"
    if cfg.point_size_space == "world":
        return "quads", (f"{src}: world-size points may cover up to 4096 px each; the compute method's cost "
                         "grows with the footprint area: quads")
    lim, ppp, where = crossover()
    if float(cfg.point_size) > lim:
        return "quads", (f"{src}: point_size {cfg.point_size} px > {lim:g} px, the largest size at which "
                         f"compute measured faster (from {where}): quads")
    px = int(cfg.size[0]) * int(cfg.size[1])
    if capacity < ppp * px:
        return "quads", (f"{src}: ring of {capacity} points < {ppp:g} points per pixel x {px} pixels, below "
                         f"which compute's per-pixel pass costs more than it saves (from {where}): quads")
    return "compute", (f"{src}: point_size {cfg.point_size} px <= {lim:g} px and {capacity} points >= "
                       f"{ppp:g} per pixel (from {where}): compute")
