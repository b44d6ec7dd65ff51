"""PPO (stable-baselines3) over VGP-Nav observations: training, evaluation and the learning curve.

``vgpnav train ppo SCENE [SCENE ...] | --task TASK [--split train] --steps N --envs E --out DIR
[--perception model|BACKBONE] [--resume]`` writes

- ``DIR/config.json``: the :func:`vgpnav_env.make_env` config of the training env (scenes,
  perception, env keyword arguments) and the seed,
- ``DIR/checkpoints/ppo_<steps>_steps.zip`` (``CheckpointCallback``), ``DIR/model.zip`` (final),
- ``DIR/tb/``: TensorBoard logs and ``progress.csv`` with ``rollout/success_rate`` and
  ``rollout/spl`` (means over the last 100 episodes) beside SB3's own entries,
- ``DIR/learning_curve.png``: success rate and SPL against env steps.

Several scenes: one per episode (:class:`~vgpnav_env.make.SceneSampler`), e.g. ``home home:1
home:2`` (procedural scenes) so that the policy generalises.

The recipe, with a perception (``model``: the privileged error model fitted to classical runs, for
RL at speed; or a pixel backbone): the policy sees the egocentric occupancy crop through a small
CNN and the goal relative to the estimated pose as (log(1 + distance), cos, sin of the bearing)
plus the localized flag (:class:`NavigationExtractor`; the absolute pose is not used, it is scene
specific), and its proprioception, the previous action and the bump sensor (``--proprioception``,
default with a perception: :mod:`vgpnav_env.agents.proprioception`; without it a blocked step
leaves the observation unchanged and the policy pushes into the wall until the episode ends).
``--randomize`` (with ``--perception model``) trains on the model's randomised episodes
(:mod:`vgpnav_env.perception.model`: the database prior's errors, long lost spells, a late first
fix; what the pixel pipeline shows in navigation); ``--init RUN_OR_ZIP`` starts from a trained
policy's weights (fine-tuning; its curriculum stage, no demonstrations) instead of a new one.
Termination is Habitat's (the env's): the episode ends when the agent stops, a success only within
the success distance. The reward is Habitat's (decrease of the geodesic distance, +2.5 on success,
-0.01 per step) minus the distance left when it stops too far and :data:`COLLISION_PENALTY` per
blocked step (:class:`EndPenalty`);
the stop action starts unlikely (:data:`STOP_LOGIT`) so that early episodes explore instead of
stopping at once. Without a perception the policy sees the raw env (camera image + world goal).
``vgpnav eval navigation SCENE --agent ppo:DIR [--perception P]`` evaluates a trained policy;
``--task pointnav-v1`` trains on the task's train split (its scenes and rules, the recipe's image size
and episode length) and ``vgpnav bench pointnav-v1 --split test --agent ppo:DIR`` reports it on test.
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
from numpy.typing import NDArray

from vgpnav_env.agents.guidance import GUIDANCE
from vgpnav_env.arguments import positive_float_arg, positive_int_arg, seed_arg
from vgpnav_env.perception.backbones import BACKBONES

logger = logging.getLogger(__name__)

#: Small images keep RL steps cheap; the CNN needs at least ~36 px per side. With a perception
#: the policy sees no image, but perception needs ``PERCEPTION_IMAGE_SIZE``.
DEFAULT_ENV_KWARGS: dict[str, Any] = {"image_size": (64, 48), "layout": "changed"}
PERCEPTION_IMAGE_SIZE = (160, 120)
#: Episodes of the perception recipe: shorter than evaluation's 500 steps (10 m goals need ~60).
PERCEPTION_ENV_KWARGS: dict[str, Any] = {"image_size": PERCEPTION_IMAGE_SIZE, "max_steps": 150}
DEFAULT_PPO_KWARGS: dict[str, Any] = {"n_steps": 128, "batch_size": 64, "n_epochs": 4, "learning_rate": 3e-4}
#: PPO settings of the perception recipe: 80 gradient steps per 512 env steps (4 epochs of 128 made
#: 16 and learned slowly: guided success 0.16 at 36k steps at 2 m goals; an update costs ~0.4 ms per
#: sample and epoch against ~6 ms per env step).
RECIPE_PPO_KWARGS: dict[str, Any] = {
    "n_steps": 256,
    "batch_size": 64,
    "n_epochs": 10,
    "learning_rate": 3e-4,
    "ent_coef": 0.01,
    "gamma": 0.99,
}
#: PPO settings a fine-tuning run (``--init``) overrides by default: a third of the recipe's
#: learning rate, and a KL target (SB3 ends an update's epochs once the approximate KL divergence
#: from the rollout's policy exceeds 1.5 x ``target_kl``): at the recipe's rate and no target,
#: fine-tuning collapsed.
FINETUNE_PPO_KWARGS: dict[str, Any] = {"learning_rate": 1e-4, "target_kl": 0.02}
PERCEPTIONS = ("model", *sorted(BACKBONES))
CONFIG_FILE = "config.json"
MODEL_FILE = "model.zip"
CURVE_FILE = "learning_curve.png"
#: Episode measures the monitor records (logged by ``ppo_policy.SuccessLogger``).
EPISODE_MEASURES = ("success", "spl")


#: Training reward charged per blocked step (the recipe's :class:`EndPenalty`).
COLLISION_PENALTY = 0.05


class EndPenalty(gym.Wrapper):
    """Training reward of the recipe: the env's (Habitat's) reward, minus the geodesic distance
    still to go when the agent stops outside the success distance, minus :data:`COLLISION_PENALTY`
    per blocked step (a blocked forward step already earns only the step penalty; this makes
    pushing into a wall cost more than turning away).

    With Habitat's reward alone a policy that cannot yet navigate learns to take a step or two
    towards the goal and stop (measured here: episodes of 4-8 steps after 7k steps, no success);
    charging the distance left makes stopping early cost what it leaves undone. Timeouts are not
    charged: their return would depend on the step count, which the policy does not see (charging
    them too left the value function unable to explain returns, explained variance ~0, and the policy
    turning in place after 70k steps).
    """

    def step(self, action: Any):
        obs, reward, terminated, truncated, info = self.env.step(action)
        if terminated and not info["success"]:
            reward -= float(info["distance_to_goal"])
        if info["blocked"]:
            reward -= COLLISION_PENALTY
        return obs, reward, terminated, truncated, info


def make_vec(config: dict[str, Any], n_envs: int, seed: int, end_penalty: bool = False):
    """Vectorised, monitored ``make_env(config)`` envs (``SubprocVecEnv`` for more than one env,
    else ``DummyVecEnv``); the monitor records each episode's success, SPL and the env's reward
    (before :class:`EndPenalty`, applied with ``end_penalty``)."""
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    from vgpnav_env.make import make_env

    if n_envs <= 0:
        raise ValueError(f"need at least one env, got {n_envs}")
    return make_vec_env(
        make_env,
        n_envs=n_envs,
        seed=seed,
        env_kwargs={"config": config},
        vec_env_cls=SubprocVecEnv if n_envs > 1 else DummyVecEnv,
        monitor_kwargs={"info_keywords": EPISODE_MEASURES},
        wrapper_class=EndPenalty if end_penalty else None,
    )


class SB3Policy:
    """A saved stable-baselines3 policy: the most likely action, or with ``sample`` one drawn from
    its action distribution (discrete actions; a generator seeded by :meth:`reset`'s episode seed);
    with ``escape_loops`` the most likely action except at a step where a
    :class:`~vgpnav_env.agents.proprioception.LoopDetector` finds it in a loop, where it is drawn.
    A policy trained with ``guidance`` computes its path channel itself from ``env`` (the
    perception-wrapped env it acts in: its ``fused_map``, as the A* agent reads it), one trained
    with ``proprioception`` its previous action and the env's bump sensor."""

    def __init__(
        self, path: str | Path, env: gym.Env | None = None, sample: bool = False, escape_loops: bool = False
    ) -> None:
        from stable_baselines3 import PPO

        from vgpnav_env.agents.guidance import path_channel_for
        from vgpnav_env.agents.ppo_policy import single_thread
        from vgpnav_env.agents.proprioception import LoopDetector, Proprioceptor

        single_thread()
        self.model = PPO.load(str(path), device="cpu")
        if (sample or escape_loops) and not isinstance(self.model.action_space, gym.spaces.Discrete):
            raise ValueError(f"sampled actions need a discrete action space, got {self.model.action_space}")
        self.env, self.sample = env, bool(sample)
        self.loops = LoopDetector() if escape_loops else None
        self.rng = np.random.default_rng()
        self.channel = self.sense = None
        config = load_config(path)["env"]
        if (config.get("guidance") is not None or config.get("proprioception")) and env is None:
            raise ValueError(f"{path} was trained with guidance or proprioception: give the env it acts in")
        if config.get("guidance") is not None:
            self.channel = path_channel_for(env, self.model.observation_space)
        if config.get("proprioception"):
            self.sense = Proprioceptor(env)

    def reset(self, seed: int | None = None) -> None:
        """Start an episode; ``seed`` (the episode's) seeds the sampled actions."""
        if self.channel is not None:
            self.channel.reset()
        if self.sense is not None:
            self.sense.reset()
        if self.loops is not None:
            self.loops.reset()
        if seed is not None:
            self.rng = np.random.default_rng(seed)

    def probabilities(self, obs: Any) -> NDArray[np.float64]:
        """The policy's action probabilities for ``obs`` as the model sees it (discrete actions)."""
        import torch

        tensor, _ = self.model.policy.obs_to_tensor(obs)
        with torch.no_grad():
            probs = self.model.policy.get_distribution(tensor).distribution.probs
        return probs[0].double().numpy()

    def act(self, obs: Any) -> Any:
        space = self.model.observation_space
        if self.sense is not None:
            obs = {**obs, **self.sense()}
        if self.channel is not None:
            obs = {**obs, **self.channel(obs, self.env.get_wrapper_attr("fused_map"))}
        if isinstance(obs, dict) and hasattr(space, "spaces"):
            obs = {key: obs[key] for key in space.spaces}  # e.g. another scene's pose bounds
        looping = False
        if self.loops is not None:
            looping = self.loops.visit(obs, self.env is not None and self.env.unwrapped.bumped)
        if self.sample or looping:
            probs = self.probabilities(obs)
            action: Any = int(self.rng.choice(len(probs), p=probs / probs.sum()))
        else:
            action, _ = self.model.predict(obs, deterministic=True)
            action = int(action) if np.ndim(action) == 0 else action
        if self.sense is not None:
            self.sense.record(action)
        if self.loops is not None:
            self.loops.record(action)
        return action


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


def run_dir_of(model: str | Path) -> Path:
    """The training run directory a model file belongs to (``DIR/model.zip`` or a checkpoint)."""
    model = Path(model)
    return next((d for d in (model.parent, model.parent.parent) if (d / CONFIG_FILE).is_file()), model.parent)


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


def train_config(
    scenes: str | list[str],
    perception: str | None = None,
    env_kwargs: dict[str, Any] | None = None,
    database_dir: str | Path | None = None,
    guidance: str | None = None,
    proprioception: bool = False,
    randomize: bool = False,
) -> dict[str, Any]:
    """The :func:`vgpnav_env.make_env` config of a training run (JSON-ready); ``randomize``: the
    ``model`` perception's randomised episodes."""
    if randomize and perception != "model":
        raise ValueError("randomize applies to the model perception")
    scenes = [scenes] if isinstance(scenes, str) else list(scenes)
    defaults = {**DEFAULT_ENV_KWARGS, **PERCEPTION_ENV_KWARGS} if perception else DEFAULT_ENV_KWARGS
    kwargs = {**defaults, **(env_kwargs or {})}
    kwargs["image_size"] = list(kwargs["image_size"])
    return {
        "scene": scenes[0] if len(scenes) == 1 else scenes,
        "perception": perception,
        "env": kwargs,
        "database_dir": str(database_dir) if database_dir is not None else None,
        "guidance": guidance,
        "proprioception": bool(proprioception),
        **({"wrapper": {"randomize": True}} if randomize else {}),
    }


#: ``vgpnav train ppo --perception P`` defaults: planner guidance and A* demonstration steps.
RECIPE_GUIDANCE = "path"
RECIPE_PRETRAIN = 3000

#: Initial logit offset of the stop action in the recipe (its probability starts at ~2%).
STOP_LOGIT = -3.0


def start_without_stopping(model) -> None:
    """Lower the initial stop logit by :data:`STOP_LOGIT`: a uniform first policy stops after ~4
    steps, so its episodes end before they learn anything but stopping (the collapse seen before)."""
    import torch

    from vgpnav_env.robot import Action

    with torch.no_grad():
        model.policy.action_net.bias[int(Action.STOP)] += STOP_LOGIT


def demonstrations(
    config: dict[str, Any], steps: int, seed: int = 0
) -> tuple[dict[str, NDArray], NDArray[np.int64]]:
    """(observations stacked per key, actions) of the A* agent (``PerceptionAStar``: the same
    estimated pose and fused map the policy has, nothing privileged) acting for ``steps`` steps in
    the training env ``config`` (its scenes in turn, the env's full goal range), the observations as
    the policy sees them (with the guidance and proprioception keys when ``config`` has them)."""
    from vgpnav_env.agents.guidance import path_channel_for
    from vgpnav_env.agents.proprioception import Proprioceptor
    from vgpnav_env.eval.navigation import PerceptionAStar
    from vgpnav_env.make import make_env

    scenes = config["scene"] if isinstance(config["scene"], list) else [config["scene"]]
    envs = [make_env({**config, "scene": s, "guidance": None, "proprioception": False}) for s in scenes]
    observations: dict[str, list] = {}
    actions: list[int] = []
    episode = 0
    try:
        while len(actions) < steps:
            env = envs[episode % len(envs)]
            agent = PerceptionAStar(env)
            channel = path_channel_for(env, env.observation_space) if config.get("guidance") else None
            sense = Proprioceptor(env) if config.get("proprioception") else None
            obs, _ = env.reset(seed=seed + episode)
            done = False
            while not done and len(actions) < steps:
                seen = {**obs, **sense()} if sense else obs
                seen = {**seen, **channel(seen, env.get_wrapper_attr("fused_map"))} if channel else seen
                for key, value in seen.items():
                    flat = np.reshape(value, -1) if np.ndim(value) == 0 else value  # Discrete: (1,)
                    observations.setdefault(key, []).append(flat)
                action = int(agent.act(obs))
                if sense:
                    sense.record(action)
                actions.append(action)
                obs, _, terminated, truncated, _ = env.step(action)
                done = terminated or truncated
            episode += 1
    finally:
        for env in envs:
            env.close()
    return {k: np.stack(v) for k, v in observations.items()}, np.asarray(actions)


def train_ppo(
    scene: str | list[str],
    steps: int,
    out_dir: str | Path,
    n_envs: int = 1,
    perception: str | None = None,
    resume: bool = False,
    seed: int = 0,
    env_kwargs: dict[str, Any] | None = None,
    ppo_kwargs: dict[str, Any] | None = None,
    checkpoint_every: int = 10_000,
    database_dir: str | Path | None = None,
    guidance: str | None = None,
    curriculum: bool = True,
    pretrain: int = 0,
    proprioception: bool = False,
    randomize: bool = False,
    init: str | Path | None = None,
) -> Path:
    """Train (or resume) PPO for ``steps`` total env steps on ``scene`` (one source or several);
    returns the final model path. With a ``perception`` the recipe of the module docstring
    (``guidance``: the planner's path channel; ``curriculum``: the goal-distance curriculum;
    ``pretrain``: env steps of A* demonstrations the new policy is first cloned from;
    ``proprioception``: the previous action and the bump sensor in the observation; ``randomize``:
    the model perception's randomised episodes; ``init``: a trained policy (run directory or
    ``.zip``, same observation) to start from, at its step count and curriculum stage, with
    :data:`FINETUNE_PPO_KWARGS` updated by ``ppo_kwargs``; a new policy takes the recipe's PPO
    settings updated by them)."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import CallbackList, CheckpointCallback
    from stable_baselines3.common.logger import configure

    from vgpnav_env.agents.ppo_policy import (
        GoalCurriculum,
        NavigationExtractor,
        SuccessLogger,
        behaviour_clone,
        single_thread,
    )
    from vgpnav_env.scenes import list_layouts

    if steps <= 0:
        raise ValueError(f"steps must be positive, got {steps}")
    if perception is not None and perception not in PERCEPTIONS:
        raise ValueError(f"unknown perception {perception!r}; allowed: {list(PERCEPTIONS)}")
    if guidance is not None and perception is None:
        raise ValueError("guidance needs a perception (it plans on the estimated map)")
    if proprioception and perception is None:
        raise ValueError("proprioception needs a perception (the raw env's observation is an image)")
    for source in [scene] if isinstance(scene, str) else scene:
        list_layouts(source)  # an unknown scene fails here, before anything is written
    single_thread()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    saved = json.loads((out / CONFIG_FILE).read_text()) if resume and (out / CONFIG_FILE).is_file() else None
    run_config = saved or {
        "env": train_config(scene, perception, env_kwargs, database_dir, guidance, proprioception, randomize),
        "seed": seed,
        "curriculum": bool(curriculum and perception is not None),
        "pretrain": int(pretrain),
        **({"init": str(model_path(init))} if init is not None else {}),
        **({"ppo": {**FINETUNE_PPO_KWARGS, **(ppo_kwargs or {})}} if init is not None else {}),
    }
    if saved is None:
        (out / CONFIG_FILE).write_text(json.dumps(run_config, indent=2) + "\n")
    config = run_config["env"]
    train_env = config
    if config["perception"] == "model":  # the policy never reads the map scores: skip their cost
        train_env = {**config, "wrapper": {**(config.get("wrapper") or {}), "map_measures": False}}
    venv = make_vec(train_env, n_envs, seed, end_penalty=config["perception"] is not None)
    ckpt = latest_checkpoint(out) if resume else None
    try:
        if ckpt is not None:
            logger.info("resuming from %s", ckpt)
            model = PPO.load(str(ckpt), env=venv, device="cpu")
        elif run_config.get("init"):
            logger.info("starting from %s with %s", run_config["init"], run_config.get("ppo"))
            model = PPO.load(run_config["init"], env=venv, device="cpu", **run_config.get("ppo", {}))
        else:
            recipe = config["perception"] is not None
            ppo = {**(RECIPE_PPO_KWARGS if recipe else DEFAULT_PPO_KWARGS), **(ppo_kwargs or {})}
            ppo["batch_size"] = min(ppo["batch_size"], ppo["n_steps"] * n_envs)
            if recipe:
                ppo["policy_kwargs"] = {
                    "features_extractor_class": NavigationExtractor,
                    "net_arch": {"pi": [128], "vf": [128]},
                }
            model = PPO("MultiInputPolicy", venv, seed=seed, device="cpu", verbose=0, **ppo)
            if recipe:
                start_without_stopping(model)
            if pretrain > 0:
                obs, actions = demonstrations(config, pretrain, seed)
                loss = behaviour_clone(model, obs, actions)
                logger.info("cloned %d A* steps: final loss %.3f", len(actions), loss)
        if ckpt is not None:
            keep_progress(out, model.num_timesteps)
        elif run_config.get("init"):
            copy_progress(run_dir_of(run_config["init"]), out, model.num_timesteps)
        model.set_logger(configure(str(out / "tb"), ["tensorboard", "csv"]))
        remaining = steps - model.num_timesteps
        if remaining > 0:
            checkpoints = CheckpointCallback(
                save_freq=max(checkpoint_every // n_envs, 1),
                save_path=str(out / "checkpoints"),
                name_prefix="ppo",
            )
            callbacks = [checkpoints, SuccessLogger()]
            if run_config.get("curriculum"):
                stage = curriculum_stage(out) if ckpt is not None else None
                if ckpt is None and run_config.get("init"):
                    stage = curriculum_stage(run_dir_of(run_config["init"]))
                callbacks.append(GoalCurriculum() if stage is None else GoalCurriculum(start=stage))
            callback = CallbackList(callbacks)
            fresh = ckpt is None and not run_config.get("init")
            model.learn(remaining, callback=callback, reset_num_timesteps=fresh)
            model.save(str(out / "checkpoints" / f"ppo_{model.num_timesteps}_steps"))
        model.save(str(out / MODEL_FILE))
    finally:
        venv.close()
    logger.info("PPO trained for %d steps -> %s", model.num_timesteps, out / MODEL_FILE)
    return out / MODEL_FILE


def progress_rows(run_dir: str | Path) -> list[dict[str, str]]:
    """The logged rows of a run (``tb/progress*.csv``: the current segment and those
    :func:`keep_progress` kept at each resumption), sorted by env steps."""
    import csv

    rows: list[dict[str, str]] = []
    for path in sorted((Path(run_dir) / "tb").glob("progress*.csv")):
        with open(path) as f:
            rows += [r for r in csv.DictReader(f) if r.get("time/total_timesteps")]
    return sorted(rows, key=lambda r: float(r["time/total_timesteps"]))


def keep_progress(run_dir: str | Path, resumed_at: int) -> None:
    """Before a resumed run's logger rewrites ``tb/progress.csv``: keep its rows up to the resumed
    checkpoint's ``resumed_at`` steps in ``tb/progress_<resumed_at>.csv``."""
    import csv

    tb = Path(run_dir) / "tb"
    current = tb / "progress.csv"
    if not current.is_file():
        return
    with open(current) as f:
        reader = csv.DictReader(f)
        fields = list(reader.fieldnames or [])
        rows = [r for r in reader if float(r.get("time/total_timesteps") or "inf") <= resumed_at]
    with open(tb / f"progress_{resumed_at:09d}.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fields)
        writer.writeheader()
        writer.writerows(rows)
    current.unlink()


def copy_progress(source: str | Path, run_dir: str | Path, until: int) -> None:
    """Copy the logged rows of the ``source`` run (up to ``until`` steps, where a run started from
    its policy begins) into ``run_dir``'s ``tb/progress_<steps>.csv`` files, so that the new run's
    learning curve continues the source's."""
    import shutil

    tb = Path(run_dir) / "tb"
    tb.mkdir(parents=True, exist_ok=True)
    for path in (Path(source) / "tb").glob("progress_*.csv"):
        if int(path.stem.split("_")[1]) <= until:
            shutil.copy(path, tb / path.name)
    if (Path(source) / "tb" / "progress.csv").is_file():
        shutil.copy(Path(source) / "tb" / "progress.csv", tb / "progress.csv")
        keep_progress(run_dir, until)


def curriculum_stage(run_dir: str | Path) -> float | None:
    """The last logged ``curriculum/max_geodesic`` of a run (None if none was logged)."""
    key = "curriculum/max_geodesic"
    stages = [r[key] for r in progress_rows(run_dir) if r.get(key)]
    return float(stages[-1]) if stages else None


def plot_learning_curve(run_dir: str | Path, out: str | Path | None = None) -> Path:
    """Success rate and SPL, and the episode return (Habitat's reward, before :class:`EndPenalty`),
    means over the last 100 episodes, against env steps, from the run's ``tb/progress*.csv``
    (dotted lines: where the run was resumed, or started from its ``init`` policy, whose rows
    :func:`copy_progress` copied in); written to ``out`` (default ``RUN/learning_curve.png``)."""
    import textwrap

    from matplotlib.figure import Figure

    run_dir = Path(run_dir)
    rows = [r for r in progress_rows(run_dir) if r.get("rollout/success_rate")]
    if not rows:
        raise ValueError(f"{run_dir}: no logged episodes yet (rollout/success_rate)")
    steps = np.array([float(r["time/total_timesteps"]) for r in rows])
    fig = Figure(figsize=(6.4, 5.6))
    ax, ax_return = fig.subplots(2, 1, sharex=True)
    for key, label in (("rollout/success_rate", "success rate"), ("rollout/spl", "SPL")):
        ax.plot(steps, [float(r[key]) for r in rows], label=label)
    ax_return.plot(steps, [float(r["rollout/ep_rew_mean"]) for r in rows], color="tab:green")
    if rows[0].get("curriculum/max_geodesic"):
        ax_goal = ax.twinx()
        limit = [float(r.get("curriculum/max_geodesic") or "nan") for r in rows]
        ax_goal.plot(steps, limit, color="tab:gray", ls="--", label="curriculum: max goal distance")
        ax_goal.set(ylabel="max goal distance (m)", ylim=(0, np.nanmax(limit) * 1.1))
        ax_goal.legend(loc="upper right")
    config = load_config(run_dir)["env"]
    scenes = config["scene"] if isinstance(config["scene"], list) else [config["scene"]]
    guided = f", {config['guidance']} guidance" if config.get("guidance") else ""
    guided += ", proprioception" if config.get("proprioception") else ""
    run = load_config(run_dir)
    cloned = f", cloned from {run['pretrain']} A* steps" if run.get("pretrain") else ""
    if run.get("init"):
        cloned += f", from {Path(run['init']).stem}"
    if run.get("ppo"):
        cloned += ", " + ", ".join(f"{k} {v:g}" for k, v in run["ppo"].items() if isinstance(v, float))
    if (config.get("wrapper") or {}).get("randomize"):
        cloned += ", randomised episodes"
    where = scenes[0] if len(scenes) == 1 else f"{scenes[0]} + {len(scenes) - 1} scenes"
    ax.set(ylabel="mean, last 100 episodes", ylim=(0, 1))
    title = f"PPO, {config['perception']} perception{guided}{cloned}, {where}"
    ax.set_title(textwrap.fill(title, 80), fontsize=9)
    for p in (run_dir / "tb").glob("progress_*.csv"):  # resumptions (keep_progress)
        for a in (ax, ax_return):
            a.axvline(int(p.stem.split("_")[1]), color="k", ls=":", lw=1)
    ax_return.set(xlabel="env steps", ylabel="episode return (Habitat reward)")
    for a in (ax, ax_return):
        a.grid(alpha=0.3)
    ax.legend(loc="upper left")
    fig.tight_layout()
    out = Path(out) if out is not None else run_dir / CURVE_FILE
    fig.savefig(out, dpi=100)
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """CLI arguments of ``vgpnav train ppo``."""
    parser.add_argument(
        "scene", nargs="*", help="one or more scene sources (home, home:7, ...): one per episode"
    )
    parser.add_argument(
        "--task",
        default=None,
        help="train on a benchmark task's split instead of SCENEs (e.g. pointnav-v1): its scenes and "
        "its rules (actions, camera, robot, success radius, layout); the recipe keeps its own image "
        "size and episode length",
    )
    parser.add_argument(
        "--split", choices=("train", "val"), default="train", help="the --task split (default train)"
    )
    parser.add_argument("--steps", type=positive_int_arg, default=100_000, help="total env steps")
    parser.add_argument("--envs", type=positive_int_arg, default=2, help="parallel envs")
    parser.add_argument("--out", type=Path, required=True, help="output directory")
    parser.add_argument(
        "--perception",
        choices=PERCEPTIONS,
        default=None,
        help="model (privileged error model, RL at speed) or a backbone (pixels); default: none (raw env)",
    )
    parser.add_argument(
        "--guidance",
        choices=(*GUIDANCE, "none"),
        default=None,
        help="path: the agent's own A* path on its estimated map as a map channel and waypoint "
        f"(hierarchical); none: plain observation (default with --perception: {RECIPE_GUIDANCE})",
    )
    parser.add_argument(
        "--no-curriculum",
        dest="curriculum",
        action="store_false",
        help="sample goals at every distance from the start (default: goal-distance curriculum)",
    )
    parser.add_argument(
        "--pretrain",
        type=int,
        default=None,
        help="clone the new policy first from this many env steps of the A* agent on the same "
        f"perception (warm start; 0: none; default with --perception: {RECIPE_PRETRAIN})",
    )
    parser.add_argument(
        "--no-proprioception",
        dest="proprioception",
        action="store_false",
        help="leave the previous action and the bump sensor out of the observation (default with "
        "--perception: in it)",
    )
    parser.add_argument(
        "--randomize",
        action="store_true",
        help="with --perception model: its randomised episodes (database prior errors, long lost "
        "spells, a late first fix: the pixel pipeline's statistics in navigation)",
    )
    parser.add_argument(
        "--init",
        type=Path,
        default=None,
        help="start from this trained policy (run directory or .zip; same observation) instead of "
        "a new one: fine-tuning, no demonstrations",
    )
    parser.add_argument(
        "--learning-rate",
        type=positive_float_arg,
        default=None,
        help=f"PPO learning rate (default: {RECIPE_PPO_KWARGS['learning_rate']:g} for a new policy, "
        f"{FINETUNE_PPO_KWARGS['learning_rate']:g} with --init)",
    )
    parser.add_argument(
        "--target-kl",
        type=positive_float_arg,
        default=None,
        help="stop an update's epochs once the approximate KL divergence exceeds 1.5 x this "
        f"(default: none for a new policy, {FINETUNE_PPO_KWARGS['target_kl']:g} with --init)",
    )
    parser.add_argument(
        "--resume",
        action="store_true",
        help="continue from the newest checkpoint (with the run's saved config and curriculum stage)",
    )
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


#: Task rules the training recipe keeps its own values of (evaluation uses the task's).
RECIPE_OWN = ("image_size", "max_steps", "min_geodesic", "max_geodesic")


def task_training(task_name: str, split: str) -> tuple[list[str], dict[str, Any]]:
    """(scene sources, env keyword arguments) of a benchmark task's split for training: the
    task's rules but :data:`RECIPE_OWN` (``vgpnav bench TASK --agent ppo:DIR`` evaluates under the
    task's full rules)."""
    from vgpnav_env.tasks import load_task
    from vgpnav_env.tasks.splits import scene_source

    task = load_task(task_name)
    scenes = [scene_source(s) for s in task.scenes(split)]
    return scenes, {k: v for k, v in task.env_kwargs().items() if k not in RECIPE_OWN}


def run(args: argparse.Namespace) -> int:
    """Entry point of ``vgpnav train ppo``; returns the process exit code."""
    env_kwargs = None
    if args.task is not None:
        if args.scene:
            raise ValueError("give SCENEs or --task, not both")
        args.scene, env_kwargs = task_training(args.task, args.split)
    elif not args.scene:
        raise ValueError("give one or more SCENEs or --task TASK")
    if args.database is not None and not args.database.is_dir():
        raise ValueError(f"--database {args.database}: no such build directory (make one with vgpnav build)")
    if args.perception == "learned":
        raise ValueError(
            "PPO trains with --perception model, classical or simulated; learned is for vgpnav eval"
        )
    if args.pretrain is not None and (args.pretrain < 0 or (args.pretrain and args.perception is None)):
        raise ValueError("--pretrain needs --perception and a non-negative number of steps")
    if args.guidance not in (None, "none") and args.perception is None:
        raise ValueError("--guidance needs --perception (it plans on the estimated map)")
    recipe = args.perception is not None
    guidance = (RECIPE_GUIDANCE if recipe else None) if args.guidance is None else args.guidance
    pretrain = (RECIPE_PRETRAIN if recipe else 0) if args.pretrain is None else args.pretrain
    if args.randomize and args.perception != "model":
        raise ValueError("--randomize needs --perception model")
    if args.init is not None and args.resume:
        raise ValueError("--init starts a new run from a policy; --resume continues this run: give one")
    if args.init is not None:
        try:
            model_path(args.init)  # a one-line error before anything is written
        except FileNotFoundError as e:
            raise ValueError(f"--init: {e}") from None
        pretrain = 0
    if args.database is not None and len(args.scene) > 1:
        raise ValueError("--database names one scene's build: give one scene")
    if args.resume and (args.learning_rate is not None or args.target_kl is not None):
        raise ValueError(
            "--resume continues with the run's saved PPO settings: no --learning-rate / --target-kl"
        )
    ppo_kwargs = {
        key: value
        for key, value in (("learning_rate", args.learning_rate), ("target_kl", args.target_kl))
        if value is not None
    }
    path = train_ppo(
        args.scene,
        args.steps,
        args.out,
        env_kwargs=env_kwargs,
        n_envs=args.envs,
        perception=args.perception,
        resume=args.resume,
        seed=args.seed,
        checkpoint_every=args.checkpoint_every,
        database_dir=args.database,
        guidance=None if guidance == "none" else guidance,
        curriculum=args.curriculum,
        pretrain=pretrain,
        proprioception=recipe and args.proprioception,
        randomize=args.randomize,
        init=args.init,
        ppo_kwargs=ppo_kwargs,
    )
    if args.perception is not None:
        print(f"learning curve: {plot_learning_curve(args.out)}")
    print(f"model: {path}")
    return 0
