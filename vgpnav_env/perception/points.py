"""Backbone depth maps to 3D points: the one place a depth map is sampled into points.

A depth map is z-depth (H, W) along the optical axis of a :class:`~vgpnav_env.geometry.PinholeCamera`
(0 or non-finite = unknown), in metres or in a backbone's units; points come out in the same
camera frame (OpenCV) and units.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vgpnav_env.geometry import PinholeCamera


def depth_points(
    camera: PinholeCamera,
    depth: ArrayLike,
    confidence: ArrayLike | None = None,
    *,
    stride: int = 1,
    min_confidence: float = 0.0,
    max_depth: float = np.inf,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Camera-frame points (N, 3) of every ``stride``-th pixel (both directions, from pixel 0) with
    finite depth in ``(0, max_depth]`` and ``confidence >= min_confidence``, and their confidences
    (N,) (1 without a confidence map), in row-major pixel order."""
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    rays = camera.rays()[::stride, ::stride]
    d = np.asarray(depth)[::stride, ::stride]
    c = np.ones(d.shape) if confidence is None else np.asarray(confidence)[::stride, ::stride]
    if d.shape != c.shape or rays.shape[:2] != d.shape:
        raise ValueError(
            f"depth {np.shape(depth)} and confidence {np.shape(confidence)} must have the camera's "
            f"shape {(camera.height, camera.width)}"
        )
    mask = np.isfinite(d) & (d > 0) & (d <= max_depth) & (c >= min_confidence)
    points = rays * d[..., None]
    return points[mask], c[mask].astype(np.float64)
