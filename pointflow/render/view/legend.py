"""What a view's picture shows that the picture itself cannot say: the camera it was drawn
with and the colour scale in use (channel, colormap, the range actually used, also when it
is automatic). The render stage puts both in every view frame's header, so a page or a
notebook widget draws axes, grid, compass, markers and the colour legend over exactly the
picture it shows (docs/views.md "Orientation and legend")."""
from __future__ import annotations

from types import SimpleNamespace
from typing import Any, Optional

import numpy as np

from ...arrays import finite_rows
from .. import colormap
from ..base import FrameInput
from ..camera import Camera
from ..rules import color_values
from .protocol import BUILTIN_COLOR

__all__ = ["camera_dict", "legend_dict", "lut_hex", "follow_dict", "view_units", "METRES"]

#: What a view labels lengths with when nothing says otherwise: pointflow's sources are in
#: metres (ROS REP 103); a map whose CRS says feet is labelled in feet (``view_units``).
METRES = {"xy": "m", "z": "m"}


def camera_dict(cam: Camera) -> dict:
    """The camera a picture was drawn with (world coordinates; camera.py's projection:
    ``perspective(fov_deg, width / height, near, far) @ look_at(eye, target, up)``)."""
    return {"eye": [float(x) for x in cam.eye], "target": [float(x) for x in cam.target],
            "up": [float(x) for x in cam.up], "fov_deg": float(cam.fov_deg), "near": float(cam.near),
            "far": float(cam.far)}


def follow_dict(ctl: Any) -> Optional[dict]:
    """``{"frame", "origin"}``: the frame a view's camera follows and where its origin is now
    in the fixed frame (the page draws that frame's axes there too); None when not following
    or its transforms are not known yet."""
    name = ctl.state.camera.follow
    ff = getattr(ctl, "follow", None)
    o = ff.origin(name) if name and ff is not None else None
    return None if o is None else {"frame": name, "origin": [float(x) for x in o]}


def view_units(maplayer: Any) -> dict:
    """The length units a view labels its grid, measures and height legend with: the map's,
    from its CRS (render/maplayer.py ``units``), else metres. An empty label: unknown."""
    u = getattr(maplayer, "units", None)
    return dict(u) if u else dict(METRES)


def legend_dict(frame: Optional[FrameInput], style: Any, units: Optional[dict] = None) -> Optional[dict]:
    """``{"color_by", "colormap", "range": [lo, hi], "auto", "unit"}`` for a colouring through a
    colormap, in world units (``z`` in ``units["z"]``, metres by default, not origin-relative;
    ``unit`` is that label for ``z``/``height`` and "" for other channels), the range by the same
    rule every tier follows (render/rules.py ``color_values``: fixed, the handoff's
    ``channel_ranges``, else the finite min/max of the points held); None for a single
    colour or a channel the ring does not hold."""
    cb = getattr(style, "color_by", None)
    if frame is None or cb in (None, "none", "rgb"):
        return None
    shift = float(frame.origin[2]) if cb in ("z", "height") else 0.0
    auto = _auto_range(frame, cb) if style.color_range == "auto" and cb in BUILTIN_COLOR else None  # "none" returned above
    if auto is not None:
        lo, hi = auto[0] + shift, auto[1] + shift
    else:
        cfg = SimpleNamespace(color_by=cb, color_range=style.color_range)
        cv = color_values(frame, cfg, np.empty(0, np.int64))
        if cv is None:
            return None
        lo, hi = float(cv[1][0]) + shift, float(cv[1][1]) + shift
    unit = (units or METRES)["z"] if cb in ("z", "height") else ""
    return {"color_by": cb, "colormap": style.colormap, "auto": style.color_range == "auto", "unit": unit,
            "range": [lo if np.isfinite(lo) else None, hi if np.isfinite(hi) else None]}


def _auto_range(frame: FrameInput, cb: str) -> tuple[float, float]:
    """rules.color_values' automatic range of ``z`` / ``ingest_time`` (finite min/max over the
    occupied slots whose position is finite, origin-relative), without its float64 copy of
    every value: the min and max of the float32 values are the same numbers (~10x faster)."""
    cap, size = int(frame.capacity), min(int(frame.capacity), int(frame.size))
    if size == cap:
        pos, t = frame.positions[:cap], frame.t_ingest_ms[:cap]
    else:
        occ = frame.occupied_slots()
        pos, t = frame.positions[occ], frame.t_ingest_ms[occ]
    ok = finite_rows(pos)
    v = pos[:, 2] if cb in ("z", "height") else t
    v = v[ok] if not ok.all() else v
    if cb == "ingest_time":
        v = v[np.isfinite(v)]
    if v.size == 0:
        return 0.0, 0.0
    return float(v.min()), float(v.max())


def lut_hex(name: str) -> str:
    """A colormap's 256 RGB entries as one hex string (``rrggbb`` x 256): the page draws its
    legend with the render stage's own table (render/colormap.py), not an approximation."""
    return colormap.lut(name)[:, :3].tobytes().hex()
