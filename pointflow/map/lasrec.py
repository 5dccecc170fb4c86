"""LAS point records (laspy's own packed records) to the map's dict of positions and channels,
the same channels and dtypes as :func:`pointflow.ingest.formats.iter_las` gives a live file."""
from __future__ import annotations

import numpy as np


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
    dims = set(point_format.dimension_names)
    out = {"positions": np.column_stack([np.asarray(pts.x, np.float64), np.asarray(pts.y, np.float64),
                                         np.asarray(pts.z, np.float64)]),
           "intensity": np.array(pts.intensity, np.uint16),
           "classification": np.array(pts.classification, np.uint8),
           "return_number": np.array(pts.return_number, np.uint8)}
    if "gps_time" in dims:
        out["gps_time"] = np.array(pts.gps_time, np.float64)
    if {"red", "green", "blue"} <= dims:
        out["rgb"] = np.column_stack([np.asarray(pts.red), np.asarray(pts.green),
                                      np.asarray(pts.blue)]).astype(np.uint16)
    return out


def las_positions(array: np.ndarray, scales, offsets) -> np.ndarray:
    """Positions of raw records (fields X, Y, Z) as laspy scales them."""
    out = np.empty((array.shape[0], 3), np.float64)
    for i, f in enumerate(("X", "Y", "Z")):
        out[:, i] = array[f] * scales[i] + offsets[i]
    return out
