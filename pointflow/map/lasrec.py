"""LAS point records (laspy's own packed records) to the map's dict of positions and channels,
the same channels and dtypes as :func:`pointflow.formats.iter_las` gives a live file."""
from __future__ import annotations

import numpy as np

from ..formats.las import las_record_channels


#: Bytes per point of each decoded LAS channel (see :func:`las_points`).
LAS_CHANNEL_BYTES = {"intensity": 2, "classification": 1, "return_number": 1, "gps_time": 8, "rgb": 6}


def las_channel_names(point_format) -> list[str]:
    dims = set(point_format.dimension_names)
    names = ["intensity", "classification", "return_number"]
    if "gps_time" in dims:
        names.append("gps_time")
    if {"red", "green", "blue"} <= dims:
        names.append("rgb")
    return names


def las_points(array: np.ndarray, point_format, scales, offsets) -> dict[str, np.ndarray]:
    """``array``: raw records of ``point_format`` (laspy's dtype). Positions are laspy's own
    scaling (X * scale + offset, float64), so they equal ``laspy.read(path).x`` exactly."""
    from laspy import ScaleAwarePointRecord

    pts = ScaleAwarePointRecord(array, point_format, np.asarray(scales), np.asarray(offsets))
    pos, ch = las_record_channels(pts, set(point_format.dimension_names), copy=True)
    return {"positions": pos, **ch}


def las_positions(array: np.ndarray, scales, offsets) -> np.ndarray:
    """Positions of raw records (fields X, Y, Z) as laspy scales them."""
    out = np.empty((array.shape[0], 3), np.float64)
    for i, f in enumerate(("X", "Y", "Z")):
        out[:, i] = array[f] * scales[i] + offsets[i]
    return out
