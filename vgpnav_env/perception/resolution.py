"""The image size perception works at.

Perception's pixel bounds (Sampson errors, plane and support distances, guided bands) and match
counts are set for 320x240 images (a focal length of 208 px at the robot's 60 deg vertical field
of view). A wider camera's images are area-downscaled to :data:`MAX_WIDTH` (aspect ratio kept)
before any feature is extracted, database and query alike, so that a 640x480 camera takes the
decisions a 320x240 one does, at its cost. Narrower images are used as they are.
``DatabaseConfig.max_width`` sets the width (None: every image at its own size).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from vgpnav_env.geometry import PinholeCamera

#: The default working width (pixels): the size perception's settings were chosen at.
MAX_WIDTH = 320


def working_size(width: int, height: int, max_width: int | None = MAX_WIDTH) -> tuple[int, int]:
    """(width, height) perception works at for images of ``width`` x ``height`` pixels: the same,
    or scaled to ``max_width`` wide (height rounded) when wider (``max_width`` None: the same)."""
    if max_width is None or width <= max_width:
        return width, height
    return max_width, max(1, round(height * max_width / width))


def describe_size(width: int, height: int, max_width: int | None = MAX_WIDTH) -> str:
    """``WxH`` of an image size for reports, with the size perception works at when smaller:
    e.g. ``640x480 (perceived at 320x240)``."""
    size = working_size(width, height, max_width)
    text = f"{width}x{height}"
    return text if size == (width, height) else f"{text} (perceived at {size[0]}x{size[1]})"


def working_camera(camera: PinholeCamera, max_width: int | None = MAX_WIDTH) -> PinholeCamera:
    """``camera`` at its :func:`working_size` (the same vertical field of view)."""
    size = working_size(camera.width, camera.height, max_width)
    return camera if size == (camera.width, camera.height) else camera.resized(*size)


def downscale(image: NDArray, camera: PinholeCamera, nearest: bool = False) -> NDArray:
    """``image`` (H, W[, C]) resized to ``camera``'s size: area-averaged (``nearest``: the nearest
    pixel, for depth maps); returned as is when it already has that size. Raises ValueError when it
    is smaller than ``camera`` in either direction (perception never upsamples)."""
    h, w = image.shape[:2]
    if (w, h) == (camera.width, camera.height):
        return image
    if w < camera.width or h < camera.height:
        raise ValueError(
            f"image of {w}x{h} pixels is smaller than the {camera.width}x{camera.height} perception works at"
        )
    interpolation = cv2.INTER_NEAREST if nearest else cv2.INTER_AREA
    return cv2.resize(np.ascontiguousarray(image), (camera.width, camera.height), interpolation=interpolation)
