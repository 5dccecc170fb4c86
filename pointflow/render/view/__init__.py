"""One home for views (docs/views.md): the protocol every view speaks (:mod:`.protocol`),
a view's controller (:mod:`.controller`), the main view's one path (:mod:`.mainview`), the
hub that draws many views in the render stage (:mod:`.hub`), the client end the view server
and the notebook both drive (:mod:`.client`), the frame encoder (:mod:`.encode`) and the
shared gestures and overlay scripts (``static/gestures.js``, ``static/overlay.js``).

The view server (pointflow/serve) and the notebook widget import this package and nothing
else of pointflow.render. The protocol's vocabulary is importable from here; the other
modules load when named (the hub needs zmq and the render tiers, the encoder Pillow).
"""
from __future__ import annotations

from pathlib import Path

from .protocol import (BUILTIN_COLOR, COLORMAPS, COMMANDS, MAX_CREDIT, MAX_VIEW_PX, SIZE_RANGE, ControlError,
                       ViewState, color_by_options, is_gone)

#: The page's and the widget's gestures (one file for both).
GESTURES_JS = Path(__file__).parent / "static" / "gestures.js"
#: The page's and the widget's overlays drawn from the view's camera: axes, grid, compass,
#: legend, pick and measure marks (one file for both).
OVERLAY_JS = Path(__file__).parent / "static" / "overlay.js"

__all__ = ["BUILTIN_COLOR", "COLORMAPS", "COMMANDS", "MAX_CREDIT", "MAX_VIEW_PX", "SIZE_RANGE", "ControlError",
           "ViewState", "color_by_options", "is_gone", "GESTURES_JS", "OVERLAY_JS"]
