"""Frames to bytes for the browser, off the render loop: JPEG while the view moves, PNG
(lossless) when it is still.

The render stage sends raw RGBA; the view server encodes here in a thread pool. Both
encoders release the GIL while they work (simplejpeg wraps libjpeg-turbo and drops the GIL
around it; Pillow's encoders run inside ``ImagingSectionEnter``), so two frames encode at
once on two cores and the event loop stays free. Choice measured in bench/bench_serve_encode.py
(docs/views.md): simplejpeg for JPEG (Pillow's JPEG is the fallback when simplejpeg is not
installed), Pillow with ``compress_level=1`` for PNG.
"""
from __future__ import annotations

import io
import time
from dataclasses import dataclass

import numpy as np

try:  # libjpeg-turbo, GIL released, RGBA input without a copy
    import simplejpeg as _simplejpeg
except ImportError:  # pragma: no cover - the serve extra installs it
    _simplejpeg = None


@dataclass
class Encoded:
    data: bytes
    mime: str
    encode_ms: float


def encode_jpeg(rgba: np.ndarray, quality: int = 80) -> bytes:
    if _simplejpeg is not None:
        return _simplejpeg.encode_jpeg(rgba, quality=quality, colorspace="RGBA", colorsubsampling="420",
                                       fastdct=True)
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(rgba[..., :3]).save(buf, format="JPEG", quality=quality)
    return buf.getvalue()


def encode_png(rgba: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    # RGB: the alpha channel is opaque everywhere; level 1 is ~3x faster than the default
    # and only ~10 % larger on these pictures (bench/bench_serve_encode.py)
    Image.fromarray(rgba[..., :3]).save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


def encode_frame(raw, width: int, height: int, moving: bool, quality: int = 80) -> Encoded:
    """``raw``: width*height*4 RGBA bytes (a buffer). JPEG when ``moving``, else PNG."""
    rgba = np.frombuffer(raw, np.uint8)
    if rgba.size != width * height * 4:
        raise ValueError(f"frame has {rgba.size} bytes, expected {width}x{height}x4 = {width * height * 4}")
    rgba = rgba.reshape(height, width, 4)
    t0 = time.perf_counter()
    if moving:
        data, mime = encode_jpeg(rgba, quality), "image/jpeg"
    else:
        data, mime = encode_png(rgba), "image/png"
    return Encoded(data, mime, (time.perf_counter() - t0) * 1e3)
