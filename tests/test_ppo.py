"""PPO training plumbing: a tiny run trains, checkpoints, resumes, saves, loads and evaluates."""

from __future__ import annotations

import json

import pytest

from vgpnav_env.agents.ppo import (
    FINETUNE_PPO_KWARGS,
    RECIPE_PPO_KWARGS,
    latest_checkpoint,
    load_config,
    model_path,
    train_ppo,
)
from vgpnav_env.eval.navigation import evaluate_navigation, evaluate_policy

TINY = {"image_size": (48, 40), "max_steps": 40}


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    out = tmp_path_factory.mktemp("ppo")
    path = train_ppo(
        "home", 256, out, n_envs=1, env_kwargs=TINY, ppo_kwargs={"n_steps": 128}, checkpoint_every=128
    )
    return out, path


@pytest.mark.slow
def test_tiny_ppo_run_saves_model_checkpoints_config_and_tensorboard(trained):
    out, path = trained
    assert path == out / "model.zip" and path.is_file()
    assert latest_checkpoint(out).name == "ppo_256_steps.zip"
    assert any((out / "tb").rglob("events.out.tfevents*"))
    config = json.loads((out / "config.json").read_text())
    assert config["env"]["scene"] == "home" and config["env"]["perception"] is None
    assert config["env"]["env"]["image_size"] == [48, 40]
    assert load_config(path) == config and model_path(out) == path


@pytest.mark.slow
def test_resume_continues_from_latest_checkpoint(trained):
    from stable_baselines3 import PPO

    out, _ = trained
    path = train_ppo("home", 384, out, n_envs=1, resume=True, env_kwargs=TINY)
    assert PPO.load(str(path), device="cpu").num_timesteps == 384
    assert latest_checkpoint(out).name == "ppo_384_steps.zip"


@pytest.mark.slow
def test_trained_policy_loads_and_evaluates(trained, tmp_path):
    out, path = trained
    report = evaluate_policy(path, episodes=2, out_dir=tmp_path / "eval")
    assert report["episodes"] == 2 and report["agent"].startswith("ppo:")
    # The rate is the share of episodes that reached the goal, and every other one says why not.
    records = report["records"]
    assert report["success_rate"] == sum(r["success"] for r in records) / 2
    assert all((r["failure"] is None) == r["success"] for r in records)
    assert all(r["steps"] <= 40 for r in report["records"])
    assert (tmp_path / "eval" / "report.json").is_file()


@pytest.mark.slow
def test_sampled_actions_follow_the_policy_distribution_and_the_episode_seed(trained):
    """``sample``: actions drawn from the policy's distribution (frequencies within 0.1 of its
    probabilities over 400 draws, ~4 standard deviations), the same draws after the same episode
    seed; without it the most likely action every time."""
    import numpy as np

    from vgpnav_env.agents.ppo import SB3Policy
    from vgpnav_env.make import make_env

    out, path = trained
    env = make_env(load_config(path)["env"])
    obs, _ = env.reset(seed=0)
    sampled, greedy = SB3Policy(path, sample=True), SB3Policy(path)
    probs = sampled.probabilities(obs)
    assert probs.shape == (4,) and probs.sum() == pytest.approx(1.0, abs=1e-6)
    sampled.reset(seed=7)
    draws = [sampled.act(obs) for _ in range(400)]
    assert np.abs(np.bincount(draws, minlength=4) / 400 - probs).max() < 0.1
    sampled.reset(seed=7)
    assert [sampled.act(obs) for _ in range(400)] == draws
    assert {greedy.act(obs) for _ in range(5)} == {int(np.argmax(probs))}
    env.close()


def test_bad_arguments():
    with pytest.raises(ValueError, match="steps must be positive"):
        train_ppo("home", 0, "unused")
    with pytest.raises(FileNotFoundError, match="config.json"):
        load_config("/nonexistent/model.zip")


def test_model_perception_recipe_trains_logs_success_and_evaluates(tmp_path):
    """The perception recipe on the privileged model: CNN over the map crop, success and SPL in
    TensorBoard's CSV, a learning curve, and evaluation through the navigation protocol."""
    from vgpnav_env.agents.ppo import plot_learning_curve
    from vgpnav_env.agents.ppo_policy import NavigationExtractor

    out = tmp_path / "recipe"
    path = train_ppo(
        ["home", "home:1"],
        256,
        out,
        n_envs=1,
        perception="model",
        env_kwargs={"image_size": (40, 30), "max_steps": 20},
        ppo_kwargs={"n_steps": 128},
    )
    from stable_baselines3 import PPO

    model = PPO.load(str(path), device="cpu")
    assert isinstance(model.policy.features_extractor, NavigationExtractor)
    header = (out / "tb" / "progress.csv").read_text().splitlines()[0].split(",")
    assert "rollout/success_rate" in header and "rollout/spl" in header
    assert plot_learning_curve(out).is_file()
    report = evaluate_navigation(
        "home", agent=f"ppo:{out}", episodes=2, perception="model", env_kwargs={"max_steps": 15}
    )
    assert report["episodes"] == 2 and report["backbone"] == "model"
    assert all(r["steps"] <= 15 for r in report["records"])


def test_end_penalty_charges_the_distance_left_on_failure_only():
    import gymnasium as gym

    from vgpnav_env.agents.ppo import EndPenalty

    plain = gym.make("VGPNav/PointGoal-v0", scene="home", image_size=(32, 24), render_rgb=False)
    wrapped = EndPenalty(gym.make("VGPNav/PointGoal-v0", scene="home", image_size=(32, 24), render_rgb=False))
    for env in (plain, wrapped):
        env.reset(seed=3)
    (_, r_plain, done, _, info), (_, r_wrapped, *_) = plain.step(0), wrapped.step(0)  # stop at the start
    assert done and not info["success"] and info["distance_to_goal"] >= 1.0
    assert r_wrapped == pytest.approx(r_plain - info["distance_to_goal"])
    start, goal = info["start"], info["goal"]
    wrapped.reset(options={"start": (goal[0], goal[1], start[2]), "goal": tuple(goal)})
    _, reward, _, _, info = wrapped.step(0)  # stop on the goal: Habitat's reward, no penalty
    assert info["success"] and reward == pytest.approx(2.5 - 0.01)


def test_guided_recipe_sees_the_path_channel_and_evaluates_on_the_protocol(tmp_path):
    """``guidance="path"`` with ``proprioception``: the policy's CNN takes the map and the
    planner's path channel, its goal features the previous action and the bump flag; the evaluated
    policy computes the channel and its proprioception itself from the protocol's env."""
    from stable_baselines3 import PPO

    out = tmp_path / "guided"
    path = train_ppo(
        "home",
        128,
        out,
        n_envs=1,
        perception="model",
        guidance="path",
        env_kwargs={"image_size": (40, 30), "max_steps": 20},
        ppo_kwargs={"n_steps": 64},
        pretrain=64,
        proprioception=True,
    )
    model = PPO.load(str(path), device="cpu")
    extractor, spaces = model.policy.features_extractor, model.observation_space.spaces
    assert extractor.guided and extractor.proprioceptive and {"path", "last_action", "bumped"} <= set(spaces)
    config = load_config(out)
    assert config["env"]["guidance"] == "path" and config["curriculum"] and config["pretrain"] == 64
    assert config["env"]["proprioception"]
    progress = (out / "tb" / "progress.csv").read_text().splitlines()
    assert "curriculum/max_geodesic" in progress[0].split(",")
    report = evaluate_navigation(
        "home",
        agent=f"ppo:{out}",
        episodes=1,
        perception="model",
        env_kwargs={"max_steps": 10},
        actions="sampled",
    )
    assert report["episodes"] == 1 and report["records"][0]["steps"] <= 10
    assert report["actions"] == "sampled" and report["settings"]["actions"] == "sampled"
    with pytest.raises(ValueError, match="guidance needs a perception"):
        train_ppo("home", 64, tmp_path / "unused", guidance="path")


def test_behaviour_cloning_fits_the_demonstrated_actions():
    """Cloning A* demonstrations (on the model perception, with guidance) raises the policy's
    likelihood of the demonstrated actions: mean NLL from ~log 4 (uniform, stop lowered) to below 0.9."""
    import numpy as np
    from stable_baselines3 import PPO

    from vgpnav_env.agents.ppo import demonstrations, make_vec, train_config
    from vgpnav_env.agents.ppo_policy import NavigationExtractor, behaviour_clone

    config = train_config("home", "model", {"image_size": (40, 30), "max_steps": 30}, guidance="path")
    obs, actions = demonstrations(config, 60, seed=0)
    assert len(actions) == 60 and obs["path"].shape == (60, *obs["map"].shape[1:])
    assert set(np.unique(actions)) <= {0, 1, 2, 3} and (actions == 1).any()
    venv = make_vec(config, 1, 0)
    model = PPO("MultiInputPolicy", venv, policy_kwargs={"features_extractor_class": NavigationExtractor})
    assert behaviour_clone(model, obs, actions, epochs=30) < 0.9
    venv.close()


def test_init_fine_tunes_a_trained_policy_on_randomised_model_episodes(tmp_path):
    """``init``: a new run starts from a trained policy's weights at its step count, no
    demonstrations; ``randomize`` puts the model's randomised episodes in the run's config."""
    import numpy as np
    from stable_baselines3 import PPO

    kwargs = {"env_kwargs": {"image_size": (40, 30), "max_steps": 20}, "ppo_kwargs": {"n_steps": 64}}
    first = train_ppo("home", 64, tmp_path / "a", n_envs=1, perception="model", proprioception=True, **kwargs)
    path = train_ppo(
        "home",
        128,
        tmp_path / "b",
        n_envs=1,
        perception="model",
        proprioception=True,
        randomize=True,
        init=first,
        **kwargs,
    )
    config = load_config(path)
    assert config["env"]["wrapper"] == {"randomize": True} and config["init"] == str(first)
    # Fine-tuning's smaller update: the default learning rate and KL target, ppo_kwargs on top.
    assert config["ppo"] == {**FINETUNE_PPO_KWARGS, "n_steps": 64}
    assert config["pretrain"] == 0
    # It continued from the init's 64 steps: its first rollout ends at 128 (a new run's at 64).
    rows = (tmp_path / "b" / "tb" / "progress.csv").read_text().splitlines()
    steps = rows[0].split(",").index("time/total_timesteps")
    assert int(rows[1].split(",")[steps]) == 128
    assert (tmp_path / "b" / "tb" / "progress_000000064.csv").is_file()  # the init's rows: one curve
    a, b = PPO.load(str(first), device="cpu"), PPO.load(str(path), device="cpu")
    moved = [
        not np.array_equal(x, y) for x, y in zip(a.policy.parameters(), b.policy.parameters(), strict=True)
    ]
    assert b.num_timesteps == 128 and any(moved)
    assert (
        b.learning_rate == FINETUNE_PPO_KWARGS["learning_rate"]
        and b.target_kl == FINETUNE_PPO_KWARGS["target_kl"]
    )
    assert a.learning_rate == RECIPE_PPO_KWARGS["learning_rate"] and a.target_kl is None
    with pytest.raises(ValueError, match="randomize applies to the model perception"):
        train_ppo("home", 64, tmp_path / "c", perception="simulated", randomize=True)


@pytest.mark.slow
def test_escape_loops_takes_the_most_likely_action_until_a_step_repeats(trained):
    """``escape_loops``: a policy pinned in place (every step blocked) that sees the same input
    takes the most likely action at the episode's first step and draws every later one from its
    distribution (frequencies within 0.1 over 400 draws), the same draws after the same seed."""
    from types import SimpleNamespace

    import numpy as np

    from vgpnav_env.agents.ppo import SB3Policy
    from vgpnav_env.make import make_env

    _, path = trained
    env = make_env(load_config(path)["env"])
    obs, _ = env.reset(seed=0)
    pinned = SimpleNamespace(unwrapped=SimpleNamespace(bumped=True))
    policy = SB3Policy(path, env=pinned, escape_loops=True)
    probs = policy.probabilities(obs)
    policy.reset(seed=3)
    actions = [policy.act(obs) for _ in range(401)]
    assert actions[0] == int(np.argmax(probs))
    assert np.abs(np.bincount(actions[1:], minlength=4) / 400 - probs).max() < 0.1
    policy.reset(seed=3)
    assert [policy.act(obs) for _ in range(401)] == actions
    env.close()
