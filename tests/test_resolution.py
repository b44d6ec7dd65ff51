"""The size perception works at: wider cameras are downscaled to 320 pixels, narrower ones kept."""

from __future__ import annotations

import numpy as np
import pytest

from vgpnav_env.geometry import PinholeCamera
from vgpnav_env.perception.resolution import MAX_WIDTH, describe_size, downscale, working_camera, working_size


@pytest.mark.parametrize(
    ("size", "max_width", "expected"),
    [
        ((640, 480), MAX_WIDTH, (320, 240)),
        ((1280, 720), MAX_WIDTH, (320, 180)),
        ((320, 240), MAX_WIDTH, (320, 240)),
        ((160, 120), MAX_WIDTH, (160, 120)),
        ((640, 480), None, (640, 480)),
        ((641, 481), 320, (320, 240)),
    ],
)
def test_working_size(size, max_width, expected) -> None:
    assert working_size(*size, max_width) == expected


def test_working_camera_keeps_the_field_of_view() -> None:
    camera = PinholeCamera(640, 480, np.deg2rad(60.0))
    small = working_camera(camera)
    assert (small.width, small.height) == (320, 240)
    assert small.fovy == camera.fovy
    assert small.focal == pytest.approx(camera.focal / 2)
    assert working_camera(small) is small


def test_downscale_averages_and_never_upsamples() -> None:
    camera = PinholeCamera(2, 1, np.deg2rad(60.0))
    image = np.array([[[0], [100], [200], [50]], [[100], [0], [0], [150]]], np.uint8)[..., 0]
    assert downscale(image, camera).tolist() == [[50, 100]]  # the mean of each 2x2 block
    assert downscale(image, camera, nearest=True).shape == (1, 2)
    small = image[:1, :2]
    assert downscale(small, camera) is small  # already the camera's size: as is
    with pytest.raises(ValueError, match="smaller than the 2x1"):
        downscale(image[:1, :1], camera)


def test_reports_name_the_size_perception_works_at() -> None:
    assert describe_size(640, 480) == "640x480 (perceived at 320x240)"
    assert describe_size(320, 240) == "320x240"
    assert describe_size(640, 480, None) == "640x480"
