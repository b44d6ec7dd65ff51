"""Visual odometry: frame-to-frame motion from two-view geometry, fused with wheel odometry."""

from __future__ import annotations

import numpy as np
import pytest

from vgpnav_env.geometry import camera_yaw_pitch, wrap_angle
from vgpnav_env.perception.odometry import VisualMotion, VisualOdometry, VOConfig, fuse_motion
from vgpnav_env.robot import base_pose
from vgpnav_env.runs import load_build


def test_visual_odometry_measures_the_yaw_change_and_heading_of_consecutive_frames(home_build):
    """The home query run (consecutive frames ~0.5 m and ~20 deg apart). Measured at 240x180, 30
    pairs: 24 matched, yaw error median 0.04 deg (max 0.65), heading error median 0.2 deg."""
    query = load_build(home_build).query
    T0 = query.poses[0]
    vo = VisualOdometry(query.camera, float(T0[2, 3]), camera_yaw_pitch(T0)[1])
    vo.reset(query.images[0])
    yaw_errors, heading_errors, n = [], [], 30
    for i in range(1, n + 1):
        motion = vo.measure(query.images[i])
        if motion is None:
            continue
        a, b = base_pose(query.poses[i - 1]), base_pose(query.poses[i])
        yaw_errors.append(abs(wrap_angle(motion.yaw - (b[2] - a[2]))))
        d = b[:2] - a[:2]
        if np.hypot(*d) > 0.2:
            heading_errors.append(abs(wrap_angle(motion.heading - (np.arctan2(d[1], d[0]) - a[2]))))
    assert len(yaw_errors) >= 0.7 * n
    assert np.degrees(np.median(yaw_errors)) < 0.5 and np.degrees(np.median(heading_errors)) < 5.0


def test_fusion_corrects_the_odometry_and_drops_outliers():
    odometry, P = np.array([0.5, 0.0, np.radians(20)]), np.diag([0.06**2, 0.03**2, np.radians(2.0) ** 2])
    truth_yaw, truth_heading = np.radians(22), np.radians(3)
    m, Q, used = fuse_motion(odometry, P, VisualMotion(truth_yaw, truth_heading, 100))
    assert used and abs(m[2] - truth_yaw) < np.radians(0.2)  # yaw: 2 deg odometry, 0.5 deg visual
    assert abs(np.arctan2(m[1], m[0]) - truth_heading) < np.radians(1.5)  # the lateral drift
    assert np.hypot(m[0], m[1]) == pytest.approx(0.5, abs=0.01)  # the length stays the odometry's
    assert Q[2, 2] < P[2, 2] and Q[1, 1] < P[1, 1]
    m, Q, used = fuse_motion(odometry, P, VisualMotion(np.radians(110), 0.0, 60))  # a wrong pair
    assert not used and np.array_equal(m, odometry) and np.array_equal(Q, P)
    # A turn in place: no displacement, so its heading is not measured; the yaw is.
    turn = np.array([0.0, 0.0, np.radians(15)])
    P_turn = np.diag([1e-6, 1e-6, np.radians(1.5) ** 2])
    m, _, used = fuse_motion(turn, P_turn, VisualMotion(np.radians(14), 2.0, 80))
    assert used and m[:2] == pytest.approx((0.0, 0.0), abs=1e-9) and m[2] < np.radians(14.5)
    assert fuse_motion(odometry, P, None)[2] is False
    with pytest.raises(ValueError, match="positive"):
        VOConfig(yaw_sigma_deg=0.0)
