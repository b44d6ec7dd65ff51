"""Planner guidance (``--guidance path``): the A* path channel in the map crop's frame, and the
goal-distance range the curriculum sets."""

from __future__ import annotations

import numpy as np
import pytest

from vgpnav_env.agents.guidance import GOAL_VALUE, PATH_VALUE, PathChannel
from vgpnav_env.grid import GridSpec
from vgpnav_env.make import make_env
from vgpnav_env.perception.occupancy import LogOddsMap


def _obs(pose, goal):
    d = np.asarray(goal, float) - pose[:2]
    bearing = np.arctan2(d[1], d[0]) - pose[2]
    return {"pose": np.asarray(pose, np.float32), "goal_rel": np.array([np.hypot(*d), bearing])}


def test_path_channel_draws_the_path_ahead_and_around_an_obstacle():
    """Empty map, robot at the origin facing +y, goal 1 m ahead: the path runs straight up the
    crop's centre column (row 0 is ahead) to the goal 10 pixels up. A wall across the way: the path
    leaves the centre column to go around it, and still ends at the goal."""
    spec = GridSpec((-2.0, -2.0), 0.05, (80, 80))
    fused = LogOddsMap(spec)
    channel = PathChannel(size=33, resolution=0.1, robot_radius=0.2)
    pose = np.array([0.0, 0.0, np.pi / 2])
    out = channel(_obs(pose, (0.0, 1.0)), fused)
    img = out["path"][0]
    assert img.shape == (33, 33)
    np.testing.assert_allclose(out["waypoint"], (0.5, 0.0), atol=0.03)  # 0.5 m ahead on the path
    rows, cols = np.nonzero(img == PATH_VALUE)
    assert set(cols) == {16} and rows.min() >= 6 and rows.max() == 16
    assert img[6, 16] == GOAL_VALUE and (img == GOAL_VALUE).sum() == 9
    wall = (np.abs(spec.centres()[..., 1] - 0.5) < 0.05) & (np.abs(spec.centres()[..., 0]) < 0.6)
    fused.logodds[wall] = 3.0
    img = channel(_obs(pose, (0.0, 1.0)), fused)["path"][0]  # newly occupied cells on the path: replans
    rows, cols = np.nonzero(img == PATH_VALUE)
    assert np.abs(cols - 16).max() >= 6  # around the 1.2 m wide wall
    assert img[6, 16] == GOAL_VALUE


def test_a_bump_turns_the_path_around_an_obstacle_the_map_does_not_hold():
    """Empty map, goal 1 m ahead: the path runs straight ahead. The bump sensor after a forward
    step marks contacts on the robot's front: the path now leaves the centre column; without the
    bump (or after a blocked turn, which is no contact ahead) it stays straight."""
    spec = GridSpec((-2.0, -2.0), 0.05, (80, 80))
    fused = LogOddsMap(spec)
    pose = np.array([0.0, 0.0, np.pi / 2])
    for last_action, bumped, around in ((1, 1, True), (1, 0, False), (2, 1, False)):
        channel = PathChannel(size=33, resolution=0.1, robot_radius=0.2)
        channel(_obs(pose, (0.0, 1.0)), fused)
        obs = {**_obs(pose, (0.0, 1.0)), "last_action": last_action, "bumped": bumped}
        rows, cols = np.nonzero(channel(obs, fused)["path"][0] == PATH_VALUE)
        assert (np.abs(cols - 16).max() >= 3) == around, (last_action, bumped)


def test_goal_range_applies_to_every_scene_of_a_sampler():
    env = make_env({"scene": ["home", "home:1"], "env": {"image_size": [32, 24], "render_rgb": False}})
    env.set_goal_range(1.0, 1.5)
    for seed in range(6):
        _, info = env.reset(seed=seed)
        assert 0.9 <= info["shortest_path_length"] <= 1.5  # string-pulled: at most the octile distance
    with pytest.raises(ValueError, match="min_geodesic"):
        env.current.unwrapped.set_goal_range(2.0, 1.0)
    env.close()
