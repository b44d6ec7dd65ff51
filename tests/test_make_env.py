"""``make_env(config)``: plain-data config, picklable, accepted by SB3 and (when installed) RLlib."""

from __future__ import annotations

import importlib.util
import pickle
from pathlib import Path

import numpy as np
import pytest

from vgpnav_env import make_env

EXAMPLE = Path(__file__).parents[1] / "docs" / "rllib_ppo.py"
TINY = {"scene": "home", "env": {"image_size": [32, 24], "max_steps": 3}}


def test_make_env_builds_the_configured_env_and_pickles_by_reference():
    assert pickle.loads(pickle.dumps(make_env)) is make_env
    config = pickle.loads(pickle.dumps(TINY))
    env = make_env(config)
    obs, _ = env.reset(seed=0)
    assert obs["rgb"].shape == (24, 32, 3)
    assert env.unwrapped.max_steps == 3 and env.unwrapped.scene_source == "home"
    again, _ = make_env(TINY).reset(seed=0)
    np.testing.assert_array_equal(again["rgb"], obs["rgb"])
    env.close()


def test_make_env_rejects_bad_configs():
    with pytest.raises(ValueError, match="unknown make_env config keys"):
        make_env({"scene": "home", "envs": {}})
    with pytest.raises(ValueError, match="unknown perception"):
        make_env({**TINY, "perception": "magic"})
    with pytest.raises(ValueError, match="needs config\\['perception'\\]"):
        make_env({**TINY, "wrapper": {"map_size": 32}})


def test_sb3_make_vec_env_accepts_make_env():
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv

    venv = make_vec_env(
        make_env,
        n_envs=2,
        seed=0,
        env_kwargs={"config": TINY},
        vec_env_cls=SubprocVecEnv,
        vec_env_kwargs={"start_method": "spawn"},
    )
    try:
        obs = venv.reset()
        assert obs["rgb"].shape == (2, 24, 32, 3)
        dones = [venv.step(np.array([2, 3]))[2] for _ in range(3)]
        assert np.asarray(dones)[2].all()  # truncated at max_steps = 3, reset at once
    finally:
        venv.close()


@pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="ray is not installed")
def test_rllib_ppo_example_runs_a_few_iterations():
    pytest.importorskip("ray.rllib", reason="ray[rllib] is not installed (it pins gymnasium 1.2.x)")
    spec = importlib.util.spec_from_file_location("rllib_ppo", EXAMPLE)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    results = example.train(iterations=2, config=TINY, num_env_runners=2)
    assert len(results) == 2
    assert results[-1]["env_runners"]["num_env_steps_sampled_lifetime"] > 0
