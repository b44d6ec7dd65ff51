"""``make_env(config)``: one env from a plain-data config, for any process or machine.

The function is top level and the config is JSON-like data (strings, numbers, lists, dicts; assets
by path), so it pickles by reference and builds the env wherever it is called: Gymnasium vector
envs, SB3 ``make_vec_env`` / ``SubprocVecEnv``, Ray RLlib's ``tune.register_env`` (whose
``EnvContext`` is a dict with the worker index; extra keys are ignored).

Config keys (all optional):

- ``scene``: a scene source (``home``, ``hospital``, procedural ``home:7``, a spec ``.yaml`` or a
  mesh-scene directory); default ``home``. A list of sources gives a :class:`SceneSampler` (one
  scene per episode, e.g. to train across procedural scenes).
- ``env``: keyword arguments of ``VGPNav/PointGoal-v0`` (``image_size`` as a list is fine).
- ``perception``: None (raw env: camera image + world goal), a backbone name of
  :data:`~vgpnav_env.perception.backbones.BACKBONES` (``VGPNavObservation``, pixels), or ``model``
  (:class:`~vgpnav_env.perception.model.ModelObservation`: PRIVILEGED, no pixel work, renders
  depth only).
- ``wrapper``: keyword arguments of the perception wrapper.
- ``database_dir``: the scene's build directory for a backbone (default: the cached build).
- ``guidance``: None, or ``path``: the agent's A* path on its estimated map as an extra observation
  channel (:mod:`vgpnav_env.agents.guidance`; needs a perception).
- ``proprioception``: True adds the previous action and the bump sensor to the observation
  (:mod:`vgpnav_env.agents.proprioception`; needs a perception); default False.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym

ENV_ID = "VGPNav/PointGoal-v0"
CONFIG_KEYS = ("scene", "env", "perception", "wrapper", "database_dir", "guidance", "proprioception")


def env_kwargs_from(config: Mapping[str, Any]) -> dict[str, Any]:
    """The env keyword arguments of ``config`` (lists made tuples where the env wants tuples)."""
    kwargs = dict(config.get("env") or {})
    if "image_size" in kwargs:
        kwargs["image_size"] = tuple(kwargs["image_size"])
    return kwargs


class SceneSampler(gym.Env):
    """Several scenes behind one env: every ``reset`` picks one uniformly (from this env's
    ``np_random``, so a seed fixes the scene and the episode); ``step`` goes to it.

    ``configs``: one :func:`make_env` config per scene, built lazily (the first at once, for the
    spaces). The spaces are the first scene's: Box bounds of positions (``pose``, ``goal``) are
    that scene's map bounds and other scenes' values may lie outside them.
    """

    def __init__(self, configs: list[Mapping[str, Any]]) -> None:
        if not configs:
            raise ValueError("SceneSampler needs at least one scene")
        self.configs = [dict(c) for c in configs]
        self.envs: list[gym.Env | None] = [make_env(self.configs[0])] + [None] * (len(configs) - 1)
        self.observation_space = self.envs[0].observation_space
        self.action_space = self.envs[0].action_space
        self.current = self.envs[0]
        self.goal_range: tuple[float, float] | None = None

    def set_goal_range(self, min_geodesic: float, max_geodesic: float) -> None:
        """The episodes' geodesic distance range (m) in every scene, from the next ``reset`` on."""
        self.goal_range = (float(min_geodesic), float(max_geodesic))
        for env in self.envs:
            if env is not None:
                env.get_wrapper_attr("set_goal_range")(*self.goal_range)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        i = int(self.np_random.integers(len(self.envs)))
        if self.envs[i] is None:
            self.envs[i] = make_env(self.configs[i])
            if self.goal_range is not None:
                self.envs[i].get_wrapper_attr("set_goal_range")(*self.goal_range)
        self.current = self.envs[i]
        return self.current.reset(seed=int(self.np_random.integers(2**31)), options=options)

    def step(self, action: Any):
        return self.current.step(action)

    def close(self) -> None:
        for env in self.envs:
            if env is not None:
                env.close()


def make_env(config: Mapping[str, Any] | None = None) -> gym.Env:
    """The env described by ``config`` (see the module docstring); ValueError for a bad value."""
    config = dict(config or {})
    unknown = sorted(set(config) - set(CONFIG_KEYS))
    if unknown:
        raise ValueError(f"unknown make_env config keys {unknown}; allowed: {list(CONFIG_KEYS)}")
    scene = config.get("scene", "home")
    if isinstance(scene, (list, tuple)):
        if config.get("database_dir") is not None:
            raise ValueError("config['database_dir'] names one scene's build: give one scene")
        return SceneSampler([{**config, "scene": s} for s in scene])
    if not isinstance(scene, str):
        raise ValueError(f"config['scene'] must be a scene source string or a list of them, got {scene!r}")
    perception = config.get("perception")
    wrapper = dict(config.get("wrapper") or {})
    kwargs = env_kwargs_from(config)
    if perception == "model":
        kwargs.setdefault("render_rgb", False)  # the model renders depth only
    env = gym.make(ENV_ID, scene=scene, **kwargs)
    if perception is None:
        for key in ("wrapper", "guidance", "proprioception"):
            if config.get(key):
                raise ValueError(f"config[{key!r}] needs config['perception']")
        return env
    guidance = config.get("guidance")
    proprioception = bool(config.get("proprioception", False))
    if perception == "model":
        from vgpnav_env.perception.model import ModelObservation

        wrapped: gym.Env = ModelObservation(env, **wrapper)
    else:
        from vgpnav_env.perception.backbones import BACKBONES
        from vgpnav_env.wrappers import VGPNavObservation

        if perception not in BACKBONES:
            raise ValueError(
                f"unknown perception {perception!r}; allowed: None, 'model' or a backbone {sorted(BACKBONES)}"
            )
        wrapped = VGPNavObservation(
            env, backbone=perception, database_dir=config.get("database_dir"), **wrapper
        )
    if proprioception:  # inside the guidance: its planner takes in the bump sensor
        from vgpnav_env.agents.proprioception import Proprioception

        wrapped = Proprioception(wrapped)
    if guidance is not None:
        from vgpnav_env.agents.guidance import GUIDANCE, PathGuidance

        if guidance not in GUIDANCE:
            raise ValueError(f"unknown guidance {guidance!r}; allowed: None or one of {list(GUIDANCE)}")
        wrapped = PathGuidance(wrapped)
    return wrapped
