"""Eye-dome lighting in the wgpu tier: the ``EdlParams`` uniform both raster methods read.

The formula is :func:`pointflow.render.rules.edl_shade` (Potree's EDL, log2 depth, 8
neighbours); the shader side is ``wgsl/edl.wgsl``. The neighbour offsets are integers
computed once here with :func:`pointflow.render.rules.edl_offsets`; shaders never recompute them.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..rules import EDL_NEIGHBOURS, EDL_SCALE, edl_offsets
from .layout import EDL_DTYPE


def params(edl_cfg: Any, width: int, height: int, row_pitch_px: int) -> np.ndarray:
    """The EdlParams record for ``render.edl`` and the output image."""
    E = np.zeros((), EDL_DTYPE)
    E["offsets"] = edl_offsets(edl_cfg.radius_px).reshape(4, 4)
    E["k"] = EDL_SCALE * float(edl_cfg.strength) / EDL_NEIGHBOURS
    E["row_pitch"], E["width"], E["height"] = row_pitch_px, width, height
    return E
