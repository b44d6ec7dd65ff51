"""Fork safety: vector envs whose workers fork after an env of this package rendered in the parent.

Each test first makes, resets and steps an env in the parent (its renderer holds a GL context),
then forks workers with Gymnasium's default context, ``gym.make_vec(vectorization_mode="async")``
and SB3's ``SubprocVecEnv(start_method="fork")``. The workers must render (their first image equals
the parent's for the same seed), step and autoreset; the parent's env keeps rendering afterwards.
"""

from __future__ import annotations

import multiprocessing

import gymnasium as gym
import numpy as np
import pytest

ENV_ID = "VGPNav/PointGoal-v0"
SIZE = (32, 24)
MAX_STEPS = 2


def _make(scene):
    return gym.make(ENV_ID, scene=scene, image_size=SIZE, max_steps=MAX_STEPS)


@pytest.fixture
def parent_env(walled_room):
    """An env that rendered in this process; yields (env, its reset image for seed 0)."""
    env = _make(walled_room)
    first, _ = env.reset(seed=0)
    env.step(1)
    yield env, first["rgb"]
    # After the fork the parent still renders the same image for the same seed.
    again, _ = env.reset(seed=0)
    np.testing.assert_array_equal(again["rgb"], first["rgb"])
    env.close()


def _check_gym_vector(envs, first_rgb) -> None:
    """Reset and step the two-env vector ``envs`` past a truncation, then close it."""
    try:
        obs, _ = envs.reset(seed=[0, 1])
        assert obs["rgb"].shape == (2, SIZE[1], SIZE[0], 3)
        np.testing.assert_array_equal(obs["rgb"][0], first_rgb)
        dones = []
        for _ in range(MAX_STEPS + 2):
            obs, _, terminated, truncated, _ = envs.step(np.array([2, 3]))
            dones.append(terminated | truncated)
        # Truncated after MAX_STEPS steps; the next step resets (Gymnasium's next-step autoreset).
        assert np.asarray(dones)[MAX_STEPS - 1].all() and not np.asarray(dones)[MAX_STEPS].any()
        assert obs["rgb"].std() > 0  # the workers really render
    finally:
        envs.close()


def test_async_vector_env_default_context_after_parent_env(parent_env, walled_room):
    assert multiprocessing.get_start_method() == "fork"  # Gymnasium's default on Linux
    env, first = parent_env
    envs = gym.vector.AsyncVectorEnv([lambda: _make(walled_room)] * 2)
    _check_gym_vector(envs, first)


def test_make_vec_async_after_parent_env(parent_env, walled_room):
    env, first = parent_env
    envs = gym.make_vec(
        ENV_ID,
        num_envs=2,
        vectorization_mode="async",
        scene=walled_room,
        image_size=SIZE,
        max_steps=MAX_STEPS,
    )
    _check_gym_vector(envs, first)


def test_sb3_subproc_vec_env_fork_after_parent_env(parent_env, walled_room):
    from stable_baselines3.common.vec_env import SubprocVecEnv

    env, first = parent_env
    venv = SubprocVecEnv([lambda: _make(walled_room)] * 2, start_method="fork")
    try:
        venv.seed(0)
        obs = venv.reset()
        np.testing.assert_array_equal(obs["rgb"][0], first)
        dones = [venv.step(np.array([2, 3]))[2] for _ in range(MAX_STEPS + 1)]
        # SB3 resets at once: done after MAX_STEPS steps, the terminal observation kept in info.
        assert np.asarray(dones)[MAX_STEPS - 1].all() and not np.asarray(dones)[MAX_STEPS].any()
        venv.seed(0)
        np.testing.assert_array_equal(venv.reset()["rgb"][0], first)
    finally:
        venv.close()
