"""PPO (stable-baselines3, ``MultiInputPolicy``) over VGP-Nav observations: training and evaluation.

``vgpnav train ppo SCENE --steps N --envs E --out DIR [--backbone simulated] [--resume]`` writes

- ``DIR/config.json``: scene, backbone and env keyword arguments (how to rebuild the env),
- ``DIR/checkpoints/ppo_<steps>_steps.zip`` (``CheckpointCallback``), ``DIR/model.zip`` (final),
- ``DIR/tb/``: TensorBoard logs.

With a ``backbone`` the env is wrapped in ``vgpnav_env.wrappers.VGPNavObservation`` (estimated
pose, goal relative to it, egocentric occupancy crop, localized flag); without one the policy sees
the raw env observation (camera image + world goal). ``--resume`` continues from the newest
checkpoint until ``N`` total steps. ``vgpnav eval navigation SCENE --agent ppo:DIR`` (or
``eval.navigation.evaluate_policy``) evaluates a trained policy with :class:`SB3Policy`.
"""

from __future__ import annotations

import argparse
import json
import logging
import re
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from vgpnav_env.arguments import positive_int_arg, seed_arg
from vgpnav_env.perception.backbones import BACKBONES

logger = logging.getLogger(__name__)

ENV_ID = "VGPNav/PointGoal-v0"
#: Small images keep RL steps cheap; the CNN needs at least ~36 px per side. With a perception
#: backbone the policy sees no image, but perception needs ``PERCEPTION_IMAGE_SIZE``.
DEFAULT_ENV_KWARGS: dict[str, Any] = {"image_size": (64, 48), "layout": "changed"}
PERCEPTION_IMAGE_SIZE = (160, 120)
DEFAULT_PPO_KWARGS: dict[str, Any] = {"n_steps": 128, "batch_size": 64, "n_epochs": 4, "learning_rate": 3e-4}
CONFIG_FILE = "config.json"
MODEL_FILE = "model.zip"


def make_env(
    scene: str, backbone: str | None = None, database_dir: str | None = None, **env_kwargs: Any
) -> gym.Env:
    """One training env: ``VGPNav/PointGoal-v0`` on ``scene``, wrapped for ``backbone`` if given
    (with the database build at ``database_dir``, default: the scene's cached build).

    Module-level so that sub-process vector envs can pickle it by reference.
    """
    env = gym.make(ENV_ID, scene=scene, **env_kwargs)
    if backbone:
        from vgpnav_env.wrappers import VGPNavObservation

        env = VGPNavObservation(env, backbone=backbone, database_dir=database_dir)
    return env


def make_vec(
    scene: str,
    n_envs: int,
    seed: int,
    backbone: str | None,
    env_kwargs: dict[str, Any],
    database_dir: str | None = None,
):
    """Vectorised, monitored envs (``SubprocVecEnv`` for more than one env, else ``DummyVecEnv``)."""
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    if n_envs <= 0:
        raise ValueError(f"need at least one env, got {n_envs}")
    return make_vec_env(
        make_env,
        n_envs=n_envs,
        seed=seed,
        env_kwargs={"scene": scene, "backbone": backbone, "database_dir": database_dir, **env_kwargs},
        vec_env_cls=SubprocVecEnv if n_envs > 1 else DummyVecEnv,
    )


class SB3Policy:
    """A saved stable-baselines3 policy acting deterministically."""

    def __init__(self, path: str | Path) -> None:
        from stable_baselines3 import PPO

        self.model = PPO.load(str(path), device="cpu")

    def reset(self) -> None:
        return None

    def act(self, obs: Any) -> Any:
        action, _ = self.model.predict(obs, deterministic=True)
        return int(action) if np.ndim(action) == 0 else action


def latest_checkpoint(out_dir: str | Path) -> Path | None:
    """Newest ``checkpoints/ppo_<steps>_steps.zip`` under ``out_dir`` (None if there is none)."""
    found = []
    for p in (Path(out_dir) / "checkpoints").glob("ppo_*_steps.zip"):
        m = re.fullmatch(r"ppo_(\d+)_steps\.zip", p.name)
        if m:
            found.append((int(m.group(1)), p))
    return max(found)[1] if found else None


def load_config(path: str | Path) -> dict[str, Any]:
    """Training config of a run directory, or of the run a model file belongs to."""
    path = Path(path)
    for d in (path, path.parent, path.parent.parent):
        if (d / CONFIG_FILE).is_file():
            return json.loads((d / CONFIG_FILE).read_text())
    raise FileNotFoundError(f"no {CONFIG_FILE} found for {path} (expected in the training output directory)")


def model_path(path: str | Path) -> Path:
    """The model file of ``path``: a ``.zip`` itself, or ``DIR/model.zip``, else the newest checkpoint."""
    path = Path(path)
    if path.is_file():
        return path
    if path.with_suffix(".zip").is_file():
        return path.with_suffix(".zip")
    if (path / MODEL_FILE).is_file():
        return path / MODEL_FILE
    ckpt = latest_checkpoint(path)
    if ckpt is None:
        raise FileNotFoundError(f"no PPO model at {path} (neither a .zip, {MODEL_FILE} nor a checkpoint)")
    return ckpt


def train_ppo(
    scene: str,
    steps: int,
    out_dir: str | Path,
    n_envs: int = 1,
    backbone: str | None = None,
    resume: bool = False,
    seed: int = 0,
    env_kwargs: dict[str, Any] | None = None,
    ppo_kwargs: dict[str, Any] | None = None,
    checkpoint_every: int = 10_000,
    database_dir: str | Path | None = None,
) -> Path:
    """Train (or resume) PPO for ``steps`` total env steps; returns the final model path."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import CheckpointCallback

    from vgpnav_env.scenes import list_layouts

    if steps <= 0:
        raise ValueError(f"steps must be positive, got {steps}")
    list_layouts(scene)  # an unknown scene fails here, before anything is written
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    defaults = {**DEFAULT_ENV_KWARGS, "image_size": PERCEPTION_IMAGE_SIZE} if backbone else DEFAULT_ENV_KWARGS
    env_kwargs = {**defaults, **(env_kwargs or {})}
    env_kwargs["image_size"] = list(env_kwargs["image_size"])
    config = {
        "scene": scene,
        "backbone": backbone,
        "database_dir": str(database_dir) if database_dir is not None else None,
        "env_kwargs": env_kwargs,
        "seed": seed,
    }
    if resume and (out / CONFIG_FILE).is_file():
        config = json.loads((out / CONFIG_FILE).read_text())
    else:
        (out / CONFIG_FILE).write_text(json.dumps(config, indent=2) + "\n")
    kwargs = {**config["env_kwargs"], "image_size": tuple(config["env_kwargs"]["image_size"])}
    venv = make_vec(config["scene"], n_envs, seed, config["backbone"], kwargs, config.get("database_dir"))
    ckpt = latest_checkpoint(out) if resume else None
    try:
        if ckpt is not None:
            logger.info("resuming from %s", ckpt)
            model = PPO.load(str(ckpt), env=venv, tensorboard_log=str(out / "tb"), device="cpu")
        else:
            ppo = {**DEFAULT_PPO_KWARGS, **(ppo_kwargs or {})}
            ppo["batch_size"] = min(ppo["batch_size"], ppo["n_steps"] * n_envs)
            model = PPO(
                "MultiInputPolicy",
                venv,
                tensorboard_log=str(out / "tb"),
                seed=seed,
                device="cpu",
                verbose=0,
                **ppo,
            )
        remaining = steps - model.num_timesteps
        if remaining > 0:
            callback = CheckpointCallback(
                save_freq=max(checkpoint_every // n_envs, 1),
                save_path=str(out / "checkpoints"),
                name_prefix="ppo",
            )
            model.learn(remaining, callback=callback, reset_num_timesteps=ckpt is None, tb_log_name="ppo")
            model.save(str(out / "checkpoints" / f"ppo_{model.num_timesteps}_steps"))
        model.save(str(out / MODEL_FILE))
    finally:
        venv.close()
    logger.info("PPO trained for %d steps -> %s", model.num_timesteps, out / MODEL_FILE)
    return out / MODEL_FILE


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """CLI arguments of ``vgpnav train ppo``."""
    parser.add_argument("scene", help="built-in scene name (e.g. home)")
    parser.add_argument("--steps", type=positive_int_arg, default=100_000, help="total env steps")
    parser.add_argument("--envs", type=positive_int_arg, default=2, help="parallel envs")
    parser.add_argument("--out", type=Path, required=True, help="output directory")
    parser.add_argument(
        "--backbone", choices=sorted(BACKBONES), default=None, help="perception backbone (default: none)"
    )
    parser.add_argument("--resume", action="store_true", help="continue from the newest checkpoint")
    parser.add_argument(
        "--database",
        type=Path,
        default=None,
        help="build directory of the scene (default: cache, built if missing)",
    )
    parser.add_argument("--seed", type=seed_arg, default=0)
    parser.add_argument(
        "--checkpoint-every", type=positive_int_arg, default=10_000, help="env steps between checkpoints"
    )


def run(args: argparse.Namespace) -> int:
    """Entry point of ``vgpnav train ppo``; returns the process exit code."""
    if args.database is not None and not args.database.is_dir():
        raise ValueError(f"--database {args.database}: no such build directory (make one with vgpnav build)")
    if args.backbone == "learned":
        raise ValueError(
            "PPO trains with --backbone classical or simulated; the learned backbone is for vgpnav eval"
        )
    train_ppo(
        args.scene,
        args.steps,
        args.out,
        n_envs=args.envs,
        backbone=args.backbone,
        resume=args.resume,
        seed=args.seed,
        checkpoint_every=args.checkpoint_every,
        database_dir=args.database,
    )
    return 0
