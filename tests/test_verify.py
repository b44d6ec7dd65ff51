"""The pose checks of perception.verify on hand-made motion results (no rendering)."""

from __future__ import annotations

import numpy as np
import pytest

from vgpnav_env.geometry import camera_pose
from vgpnav_env.perception.motion_averaging import MotionResult
from vgpnav_env.perception.scale_recovery import GroundAnchor, ScaleEstimate
from vgpnav_env.perception.verify import VerifyConfig, check_height, check_scale


def _motion(z: float, reason: str = "") -> MotionResult:
    T = camera_pose([1.0, 2.0, z], 0.0, np.deg2rad(20.0))
    return MotionResult(T, np.ones(3), np.ones(3, bool), 3, True, reason)


def test_check_height_rejects_a_pose_off_the_calibrated_camera_height() -> None:
    anchor, config = GroundAnchor(), VerifyConfig(pose_height_tolerance=0.3)
    assert check_height(_motion(2.0), anchor, 1.2, config).ok  # no anchor yet: no check
    anchor.initialize([(_motion(1.2).T_wq, None)], 1.2)  # floor at z = 0
    assert check_height(_motion(1.45), anchor, 1.2, config).ok
    high = _motion(1.6)
    failed = check_height(high, anchor, 1.2, config)
    assert not failed.ok and failed.reason == "camera height off by +0.40 m"
    assert high.ok and high.reason == ""  # a new result: the input is not changed
    assert check_height(_motion(1.6, "single reference"), anchor, 1.2, config).ok  # no metric height
    assert check_height(high, anchor, 1.2, VerifyConfig(pose_height_tolerance=None)).ok
    with pytest.raises(ValueError, match="pose_height_tolerance"):
        VerifyConfig(pose_height_tolerance=0.0)


def test_check_scale_replaces_a_ground_scale_far_from_the_rays() -> None:
    config = VerifyConfig(scale_check_ratio=1.5)
    ground = ScaleEstimate(2.0, "ground")
    assert check_scale(ground, 1.5, config) is ground  # within 1.5x
    assert check_scale(ground, 1.0, config) == ScaleEstimate(1.0, "fallback")  # 2x: a table top
    assert check_scale(ground, float("nan"), config) is ground  # no ray scale to check against
    assert check_scale(ScaleEstimate(1.0, "disabled"), 5.0, config).source == "disabled"
    assert check_scale(ground, 1.0, VerifyConfig(scale_check_ratio=None)) is ground
    with pytest.raises(ValueError, match="scale_check_ratio"):
        VerifyConfig(scale_check_ratio=1.0)
