"""Writing a frame to an image file whose format its suffix names (``Pipeline.save_frame``).

A ``.jpg`` must hold JPEG bytes, not a PNG under the wrong name: viewers and upload forms
trust the suffix. Any other suffix is refused before the request reaches the render stage."""
from __future__ import annotations

import os

import numpy as np

#: suffix -> Pillow format
FORMATS = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG"}


def image_format(path: str) -> str:
    """The Pillow format for ``path``'s suffix; ValueError naming the path and the suffixes."""
    suffix = os.path.splitext(str(path))[1].lower()
    fmt = FORMATS.get(suffix)
    if fmt is None:
        got = f"ends in {suffix!r}" if suffix else "has no suffix"
        raise ValueError(f"save_frame: path {str(path)!r} {got}; expected one of {', '.join(FORMATS)}")
    return fmt


def write_image(path: str, rgba: np.ndarray) -> None:
    """Write ``rgba`` (h, w, 4 uint8) to ``path`` in its suffix's format, atomically."""
    from PIL import Image

    fmt = image_format(path)
    img = Image.fromarray(np.ascontiguousarray(rgba), "RGBA")
    tmp = path + ".tmp"
    if fmt == "JPEG":  # no alpha in JPEG
        img.convert("RGB").save(tmp, format="JPEG", quality=92)
    else:
        img.save(tmp, format="PNG", compress_level=1)
    os.replace(tmp, path)  # readers never see a half-written file
