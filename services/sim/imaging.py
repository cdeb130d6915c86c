"""Encoding RGB frames as JPEG or PNG bytes for HTTP responses and the frame stream."""

from __future__ import annotations

import io
from typing import Literal

import numpy as np
from PIL import Image

MEDIA_TYPES = {"jpeg": "image/jpeg", "png": "image/png"}


def encode_image(
    rgb: np.ndarray, image_format: Literal["jpeg", "png"], *, jpeg_quality: int = 80
) -> bytes:
    """Encode an (H, W, 3) uint8 array; PNG uses fast compression (level 1)."""
    buffer = io.BytesIO()
    image = Image.fromarray(np.ascontiguousarray(rgb, dtype=np.uint8))
    if image_format == "jpeg":
        image.save(buffer, format="JPEG", quality=jpeg_quality)
    else:
        image.save(buffer, format="PNG", compress_level=1)
    return buffer.getvalue()
