"""``make_env(config)``: one env from a plain-data config, for any process or machine.

The function is top level and the config is JSON-like data (strings, numbers, lists, dicts; assets
by path), so it pickles by reference and builds the env wherever it is called: Gymnasium vector
envs, SB3 ``make_vec_env`` / ``SubprocVecEnv``, Ray RLlib's ``tune.register_env`` (whose
``EnvContext`` is a dict with the worker index; extra keys are ignored).

Config keys (all optional):

- ``scene``: a scene source (``home``, ``hospital``, procedural ``home:7``, a spec ``.yaml`` or a
  mesh-scene directory); default ``home``.
- ``env``: keyword arguments of ``VGPNav/PointGoal-v0`` (``image_size`` as a list is fine).
- ``perception``: None (raw env: camera image + world goal), a backbone name of
  :data:`~vgpnav_env.perception.backbones.BACKBONES` (``VGPNavObservation``).
- ``wrapper``: keyword arguments of the perception wrapper.
- ``database_dir``: the scene's build directory for a backbone (default: the cached build).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym

ENV_ID = "VGPNav/PointGoal-v0"
CONFIG_KEYS = ("scene", "env", "perception", "wrapper", "database_dir")


def env_kwargs_from(config: Mapping[str, Any]) -> dict[str, Any]:
    """The env keyword arguments of ``config`` (lists made tuples where the env wants tuples)."""
    kwargs = dict(config.get("env") or {})
    if "image_size" in kwargs:
        kwargs["image_size"] = tuple(kwargs["image_size"])
    return kwargs


def make_env(config: Mapping[str, Any] | None = None) -> gym.Env:
    """The env described by ``config`` (see the module docstring); ValueError for a bad value."""
    config = dict(config or {})
    unknown = sorted(set(config) - set(CONFIG_KEYS))
    if unknown:
        raise ValueError(f"unknown make_env config keys {unknown}; allowed: {list(CONFIG_KEYS)}")
    scene = config.get("scene", "home")
    if not isinstance(scene, str):
        raise ValueError(f"config['scene'] must be a scene source string, got {scene!r}")
    env = gym.make(ENV_ID, scene=scene, **env_kwargs_from(config))
    perception = config.get("perception")
    wrapper = dict(config.get("wrapper") or {})
    if perception is None:
        if wrapper:
            raise ValueError("config['wrapper'] needs config['perception']")
        return env
    from vgpnav_env.perception.backbones import BACKBONES
    from vgpnav_env.wrappers import VGPNavObservation

    if perception not in BACKBONES:
        raise ValueError(
            f"unknown perception {perception!r}; allowed: None, 'model' or a backbone {sorted(BACKBONES)}"
        )
    return VGPNavObservation(env, backbone=perception, database_dir=config.get("database_dir"), **wrapper)
