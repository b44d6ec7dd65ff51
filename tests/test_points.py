"""Depth maps to points: strides, masks and the camera frame."""

from __future__ import annotations

import numpy as np
import pytest

from vgpnav_env.geometry import PinholeCamera
from vgpnav_env.perception.points import depth_points

CAMERA = PinholeCamera(8, 6, np.deg2rad(60.0))


def test_depth_points_keeps_strided_confident_pixels_in_range() -> None:
    depth = np.full((6, 8), 2.0, np.float32)
    depth[0, 0], depth[0, 2], depth[2, 0] = 0.0, np.nan, 9.0  # unknown, unknown, too far
    conf = np.full((6, 8), 0.9, np.float32)
    conf[2, 2] = 0.1  # not confident
    points, c = depth_points(CAMERA, depth, conf, stride=2, min_confidence=0.3, max_depth=5.0)
    # 3 x 4 strided pixels, 4 of them dropped; row-major order, z = depth in the camera frame.
    assert points.shape == (8, 3) and c.dtype == np.float64
    np.testing.assert_allclose(points[:, 2], 2.0)
    np.testing.assert_allclose(c, 0.9, rtol=1e-6)
    np.testing.assert_allclose(points[0], CAMERA.backproject(depth)[0, 4])
    # Without confidence or limits: every pixel with finite positive depth, confidence 1.
    points, c = depth_points(CAMERA, depth)
    assert len(points) == 6 * 8 - 2 and np.all(c == 1.0)
    with pytest.raises(ValueError, match="camera's shape"):
        depth_points(CAMERA, depth[:4])
