"""The robot description: actions, motion model, camera pose."""

from __future__ import annotations

import numpy as np
import pytest

from vgpnav_env.geometry import camera_yaw_pitch
from vgpnav_env.robot import (
    CAMERA_HEIGHT,
    CAMERA_PITCH_DEG,
    FORWARD_STEP,
    ROBOT_RADIUS,
    TURN_STEP_DEG,
    Action,
    action_path,
    base_pose,
    camera_T_wc,
    predict_pose,
)


def test_actions_are_the_env_integers():
    assert [int(a) for a in Action] == [0, 1, 2, 3]
    assert Action(1) is Action.FORWARD and Action.TURN_RIGHT == 3


def test_predict_pose_moves_forward_and_turns_with_wrapped_yaw():
    np.testing.assert_allclose(predict_pose((1.0, 2.0, np.pi / 2), Action.FORWARD), (1.0, 2.25, np.pi / 2))
    np.testing.assert_array_equal(predict_pose((1.0, 2.0, 0.3), Action.STOP), (1.0, 2.0, 0.3))
    left = predict_pose((0.0, 0.0, np.pi - 0.1), Action.TURN_LEFT)
    assert left[2] == pytest.approx(np.pi - 0.1 + np.radians(TURN_STEP_DEG) - 2 * np.pi)
    assert -np.pi <= left[2] < np.pi
    right = predict_pose((0.0, 0.0, 0.0), 3, forward_step=0.5, turn_step=0.2)
    np.testing.assert_allclose(right, (0.0, 0.0, -0.2))
    np.testing.assert_allclose(predict_pose((0.0, 0.0, 0.0), 1, forward_step=0.5), (0.5, 0.0, 0.0))


def test_predict_pose_is_the_end_of_the_collision_checked_path():
    pose = np.array([3.0, -1.0, 2.5])
    for action in (Action.FORWARD, Action.TURN_LEFT, Action.TURN_RIGHT):
        path, length = action_path(pose, action)
        np.testing.assert_array_equal(path(0.0), pose)
        end = path(1.0)
        end[2] = np.angle(np.exp(1j * end[2]))
        np.testing.assert_allclose(predict_pose(pose, action), end, atol=1e-12)
        expected = FORWARD_STEP if action == Action.FORWARD else np.radians(TURN_STEP_DEG) * ROBOT_RADIUS
        assert length == pytest.approx(expected)
    assert action_path(pose, Action.STOP) is None
    with pytest.raises(ValueError):
        action_path(pose, 7)


def test_camera_pose_and_base_pose_are_inverse():
    pose = np.array([1.5, -2.0, 0.7])
    T = camera_T_wc(pose)
    np.testing.assert_allclose(T[:3, 3], (1.5, -2.0, CAMERA_HEIGHT))
    yaw, pitch = camera_yaw_pitch(T)
    assert yaw == pytest.approx(0.7) and pitch == pytest.approx(np.radians(CAMERA_PITCH_DEG))
    np.testing.assert_allclose(base_pose(T), pose, atol=1e-12)
