"""The point-goal environment: robot motion and collisions, episodes, spaces, determinism, errors."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from vgpnav_env.envs.body import PlanarRobot, add_robot
from vgpnav_env.envs.topdown import LEGEND, legend_panel, text_panel
from vgpnav_env.geometry import camera_yaw_pitch
from vgpnav_env.robot import arc_path, straight_path, turn_path
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


# -- the Gymnasium environment -------------------------------------------------------------------

ENV_ID = "VGPNav/PointGoal-v0"
SMALL = (64, 48)


@pytest.fixture(scope="module")
def room_env(walled_room):
    env = gym.make(ENV_ID, scene=walled_room, image_size=SMALL, render_mode="rgb_array", max_steps=50)
    yield env
    env.close()


@pytest.fixture(scope="module")
def home_env():
    env = gym.make(ENV_ID, scene="home", image_size=SMALL)
    yield env
    env.close()


def test_registered_env_passes_gymnasium_and_sb3_checkers(walled_room):
    from gymnasium.utils.env_checker import check_env as gym_check
    from stable_baselines3.common.env_checker import check_env as sb3_check

    env = gym.make(ENV_ID, scene=walled_room, image_size=SMALL, render_mode="rgb_array")
    gym_check(env.unwrapped, skip_render_check=False)
    sb3_check(env.unwrapped, warn=False)
    cont = gym.make(ENV_ID, scene=walled_room, image_size=SMALL, action_mode="continuous")
    gym_check(cont.unwrapped)
    sb3_check(cont.unwrapped, warn=False)
    env.close()
    cont.close()


def test_spaces_and_info_contract(room_env):
    obs, info = room_env.reset(seed=3)
    assert room_env.observation_space.contains(obs)
    assert obs["rgb"].shape == (SMALL[1], SMALL[0], 3) and obs["rgb"].dtype == np.uint8
    assert obs["rgb"].std() > 5  # a real image, not a blank one
    np.testing.assert_allclose(obs["goal"], info["goal"], atol=1e-6)
    for key in (
        "pose",
        "T_wc",
        "depth",
        "distance_to_goal",
        "success",
        "spl",
        "soft_spl",
        "collisions",
        "steps",
    ):
        assert key in info
    # The camera sits at 1.2 m on the robot, looking along its heading, pitched 20 deg down.
    T = info["T_wc"]
    np.testing.assert_allclose(T[:3, 3], [*info["pose"][:2], 1.2], atol=1e-9)
    yaw, pitch = camera_yaw_pitch(T)
    assert yaw == pytest.approx(info["pose"][2], abs=1e-9) and pitch == pytest.approx(
        np.radians(20), abs=1e-9
    )
    # Depth is metric: pixels of the bottom rows hit the floor (z ~ 0) when back-projected.
    cam = room_env.unwrapped.camera
    pts = cam.backproject_world(info["depth"], T)
    floor_rows = cam.backproject(np.where(np.isfinite(info["depth"]), info["depth"], 0))[-3:]
    assert floor_rows.shape[0] == 3
    assert np.percentile(pts[:, 2], 5) == pytest.approx(0.0, abs=0.02)
    # Episode constraints: geodesic distance in [1, 10] m, start on the navigable component.
    assert 1.0 <= info["distance_to_goal"] <= 10.0
    assert info["shortest_path_length"] <= info["distance_to_goal"] + 1e-6
    nav, spec = room_env.unwrapped.world.navigable, room_env.unwrapped.ground_truth.spec
    r, c = spec.world_to_cell(info["pose"][:2])
    assert nav[r, c]


def test_same_seed_same_episode_and_observations(room_env):
    obs_a, info_a = room_env.reset(seed=11)
    step_a = room_env.step(1)[0]["rgb"]
    obs_b, info_b = room_env.reset(seed=11)
    step_b = room_env.step(1)[0]["rgb"]
    np.testing.assert_array_equal(info_a["start"], info_b["start"])
    np.testing.assert_array_equal(info_a["goal"], info_b["goal"])
    np.testing.assert_array_equal(obs_a["rgb"], obs_b["rgb"])
    np.testing.assert_array_equal(step_a, step_b)
    starts = {tuple(room_env.reset(seed=s)[1]["start"].round(3)) for s in range(6)}
    assert len(starts) >= 5


def test_walking_into_wall_is_blocked_and_counted(room_env):
    # The inner wall fills y in [2.45, 2.55] for x in [0, 3]; the robot drives north into it.
    _, info = room_env.reset(options={"start": (1.0, 1.5, np.pi / 2), "goal": (3.5, 4.0)})
    start_distance = info["distance_to_goal"]
    rewards = []
    for _ in range(8):
        _, reward, terminated, truncated, info = room_env.step(1)
        rewards.append(reward)
        assert not (terminated or truncated)
    assert info["pose"][1] == pytest.approx(2.25, abs=0.01)
    assert info["pose"][1] < 2.45
    assert info["collisions"] >= 4 and info["blocked"]
    assert info["travelled"] == pytest.approx(0.75, abs=0.01)
    # Reward = decrease of geodesic distance - 0.01 per step (no success).
    assert sum(rewards) == pytest.approx(start_distance - info["distance_to_goal"] - 0.08, abs=1e-6)
    assert rewards[-1] == pytest.approx(-0.01, abs=1e-6)


def test_stop_success_spl_and_truncation(room_env):
    _, info = room_env.reset(options={"start": (3.5, 1.0, np.pi / 2), "goal": (3.5, 2.0)})
    for _ in range(3):
        room_env.step(1)
    _, reward, terminated, truncated, info = room_env.step(0)
    assert terminated and not truncated and info["success"] and info["stopped"]
    assert info["euclidean_distance_to_goal"] == pytest.approx(0.25, abs=1e-6)
    assert info["spl"] == pytest.approx(1.0)  # travelled 0.75 m < shortest 1 m
    assert reward == pytest.approx(2.5 - 0.01)  # stopping does not move
    with pytest.raises(RuntimeError, match="reset"):
        room_env.step(1)
    room_env.reset(options={"start": (3.5, 1.0, np.pi / 2), "goal": (3.5, 2.0)})
    _, _, terminated, _, info = room_env.step(0)
    assert terminated and not info["success"] and info["spl"] == 0.0 and info["soft_spl"] == 0.0
    short = gym.make(ENV_ID, scene=room_env.unwrapped.world.scene, image_size=SMALL, max_steps=3)
    short.reset(seed=0)
    results = [short.step(2) for _ in range(3)]
    assert [r[3] for r in results] == [False, False, True] and not any(r[2] for r in results)
    short.close()


def test_continuous_actions(walled_room):
    env = gym.make(ENV_ID, scene=walled_room, image_size=SMALL, action_mode="continuous")
    env.reset(options={"start": (3.5, 1.0, np.pi / 2), "goal": (3.5, 4.0)})
    _, _, _, _, info = env.step(np.array([1.0, 0.0, -1.0], np.float32))
    np.testing.assert_allclose(info["pose"], [3.5, 1.25, np.pi / 2], atol=1e-9)
    _, _, _, _, info = env.step(np.array([0.0, 1.0, -1.0], np.float32))
    assert info["pose"][2] == pytest.approx(np.pi / 2 + np.radians(15))
    _, _, terminated, _, info = env.step(np.array([0.0, 0.0, 1.0], np.float32))
    assert terminated and info["stopped"]
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"\[-1, 1\]"):
        env.step(np.array([2.0, 0.0, 0.0]))
    env.close()


def test_bad_inputs_give_clear_errors(room_env):
    from vgpnav_env.scenes import SceneError

    with pytest.raises(SceneError):
        gym.make(ENV_ID, scene="no-such-scene")
    with pytest.raises(ValueError, match="action_mode"):
        gym.make(ENV_ID, scene=room_env.unwrapped.world.scene, action_mode="teleport")
    fresh = gym.make(ENV_ID, scene=room_env.unwrapped.world.scene, image_size=SMALL)
    with pytest.raises(RuntimeError, match="reset"):
        fresh.unwrapped.step(1)
    fresh.close()
    room_env.reset(seed=0)
    for bad in (4, -1, 1.5, "forward", [1, 2]):
        with pytest.raises(ValueError, match="0-3"):
            room_env.unwrapped.step(bad)
    with pytest.raises(ValueError, match="collides"):
        room_env.reset(options={"start": (1.0, 2.5, 0.0), "goal": (3.5, 4.0)})


def test_render_shows_view_and_top_down_map_with_overlay(room_env):
    room_env.reset(seed=1)
    frame = room_env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[0] >= 360
    assert frame.shape[1] > frame.shape[0]  # camera view plus the map beside it
    base = room_env.unwrapped.top_down(200)
    room_env.unwrapped.set_overlay(estimated_pose=(2.0, 2.0, 0.0), path=[(0.5, 0.5), (3.5, 4.5)])
    assert (room_env.unwrapped.top_down(200) != base).any(axis=-1).sum() > 50


def test_render_has_a_status_line_and_a_legend(room_env):
    env = room_env.unwrapped
    env.reset(seed=1)
    assert env.status_line().startswith("step 0/") and "action: none yet" in env.status_line()
    assert "true pose (no perception)" in env.status_line()
    bare = env.render()
    env.step(2)  # turn left
    pose = env.pose
    env.set_overlay(estimated_pose=pose + [0.3, 0.4, 0.0], localized=False)
    line = env.status_line()
    assert "step 1/" in line and "action: turn left" in line
    assert "LOST (odometry), pose error 0.50 m" in line
    assert f"goal {env.measurements['distance_to_goal'].metric:.2f} m" in line and "collisions 0" in line
    env.set_overlay(localized=True)
    assert "localized, pose error 0.50 m" in env.status_line()
    frame = env.render()
    width = frame.shape[1]
    strips = frame[-(text_panel(["x"], width).shape[0] + legend_panel(width).shape[0]) :]
    assert frame.shape == bare.shape and len(strips) > 40  # strips under the pictures
    assert (strips == (35, 35, 35)).all(axis=-1).mean() > 0.5  # dark panel ...
    for _, colour, _ in LEGEND:  # ... with every legend swatch in it
        assert (strips == colour).all(axis=-1).any(), colour


def test_home_episodes_respect_distance_range(home_env):
    ratios = []
    for seed in range(8):
        _, info = home_env.reset(seed=seed)
        assert 1.0 <= info["distance_to_goal"] <= 10.0
        ratios.append(info["distance_to_goal"] / np.linalg.norm(info["start"][:2] - info["goal"]))
    assert np.mean(np.asarray(ratios) < 1.1) <= 0.5  # near-straight pairs are down-weighted


def test_async_vector_env_steps_and_autoresets(walled_room):
    envs = gym.vector.AsyncVectorEnv(
        # "module:id" makes the spawned workers import vgpnav_env (which registers the env).
        [lambda: gym.make(f"vgpnav_env:{ENV_ID}", scene=walled_room, image_size=(32, 24), max_steps=2)] * 2,
        context="spawn",
    )
    try:
        obs, _ = envs.reset(seed=[0, 1])
        assert obs["rgb"].shape == (2, 24, 32, 3)
        dones = []
        for _ in range(4):
            obs, _, terminated, truncated, _ = envs.step(np.array([2, 3]))
            dones.append(terminated | truncated)
        assert np.asarray(dones)[1].all()  # truncated after 2 steps, then reset on the next step
        assert obs["rgb"].shape == (2, 24, 32, 3)
    finally:
        envs.close()
