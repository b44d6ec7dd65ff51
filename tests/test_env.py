"""The point-goal environment: robot motion and collisions, episodes, spaces, determinism, errors."""

from __future__ import annotations

import numpy as np
import pytest

from vgpnav_env.envs.robot import PlanarRobot, add_robot, arc_path, straight_path, turn_path
from vgpnav_env.scenes.model import build_mjspec


@pytest.fixture(scope="module")
def walled_robot(walled_room) -> PlanarRobot:
    spec = build_mjspec(walled_room)
    add_robot(spec, radius=0.2, height=1.3)
    return PlanarRobot(spec.compile())


def test_robot_is_blocked_by_wall_and_stops_at_contact(walled_robot):
    # Inner wall occupies y in [2.45, 2.55] for x in [0, 3]; the hull radius is 0.2 m.
    robot = walled_robot
    robot.set_pose([1.0, 1.5, np.pi / 2])
    assert not robot.in_collision()
    blocked_steps = 0
    for _ in range(8):
        _, blocked = robot.move_along(straight_path(robot.pose, 0.25), 0.25)
        blocked_steps += blocked
    assert blocked_steps >= 4
    assert robot.pose[1] == pytest.approx(2.45 - 0.2, abs=0.01)
    assert not robot.in_collision()


def test_robot_passes_through_gap_and_turns_freely(walled_robot):
    robot = walled_robot
    robot.set_pose([3.5, 1.5, np.pi / 2])  # the gap is x in (3, 4)
    for _ in range(8):
        fraction, blocked = robot.move_along(straight_path(robot.pose, 0.25), 0.25)
        assert (fraction, blocked) == (1.0, False)
    assert robot.pose[1] == pytest.approx(3.5)
    fraction, blocked = robot.move_along(turn_path(robot.pose, np.radians(15)), 0.05)
    assert not blocked and robot.pose[2] == pytest.approx(np.pi / 2 + np.radians(15))


def test_arc_path_matches_unicycle_integration():
    end = arc_path([0.0, 0.0, 0.0], v=1.0, omega=np.pi / 2, dt=1.0)(1.0)
    r = 1.0 / (np.pi / 2)
    np.testing.assert_allclose(end, [r, r, np.pi / 2], atol=1e-12)
    np.testing.assert_allclose(arc_path([1.0, 2.0, 0.0], 0.5, 0.0, 2.0)(0.5), [1.5, 2.0, 0.0])


def test_robot_rejects_model_without_robot(walled_room):
    with pytest.raises(ValueError, match="no robot body"):
        PlanarRobot(build_mjspec(walled_room).compile())
