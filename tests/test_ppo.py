"""PPO training plumbing: a tiny run trains, checkpoints, resumes, saves, loads and evaluates."""

from __future__ import annotations

import json

import pytest

from vgpnav_env.agents.ppo import latest_checkpoint, load_config, model_path, train_ppo
from vgpnav_env.eval.navigation import evaluate_policy

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
    assert config["scene"] == "home" and config["backbone"] is None
    assert config["env_kwargs"]["image_size"] == [48, 40]
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


def test_bad_arguments():
    with pytest.raises(ValueError, match="steps must be positive"):
        train_ppo("home", 0, "unused")
    with pytest.raises(FileNotFoundError, match="config.json"):
        load_config("/nonexistent/model.zip")
