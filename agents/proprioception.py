"""Proprioception for learned policies: the previous action and the bump sensor.

A memoryless policy whose forward step is blocked sees the same observation again (the pose and
the map do not change) and repeats the blocked action until the episode times out (measured: 13 of
14 failures of the PPO recipe's policy on home pushed into walls, 150-460 collisions per episode).
:class:`Proprioception` adds what a robot knows about its own body:

- ``last_action`` (``Discrete(len(Action))``): the action of the previous step, ``Action.STOP``
  at an episode's first step (a stop ends the episode, so it never precedes a step otherwise);
- ``bumped`` (``Discrete(2)``): 1 if the previous step's motion was blocked, the env's bump sensor
  (:attr:`~vgpnav_env.envs.pointgoal.PointGoalEnv.bumped`), not the true pose.

:class:`Proprioceptor` computes them for a policy acting in an env without the wrapper
(``SB3Policy``), as the wrapper does during training.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
from gymnasium import spaces

from vgpnav_env.robot import Action

#: Observation keys added by :class:`Proprioception`.
LAST_ACTION_KEY, BUMPED_KEY = "last_action", "bumped"


def proprioception_spaces() -> dict[str, spaces.Discrete]:
    """The spaces of the keys :class:`Proprioception` adds."""
    return {LAST_ACTION_KEY: spaces.Discrete(len(Action)), BUMPED_KEY: spaces.Discrete(2)}


class Proprioceptor:
    """The proprioceptive keys of ``env`` (discrete actions): call :meth:`reset` at an episode's
    start and :meth:`record` with every action taken."""

    def __init__(self, env: gym.Env) -> None:
        if not isinstance(env.action_space, spaces.Discrete):
            raise ValueError(f"proprioception needs discrete actions, got {env.action_space}")
        self.env = env
        self.reset()

    def reset(self) -> None:
        self.last_action = int(Action.STOP)

    def record(self, action: Any) -> None:
        self.last_action = int(action)

    def __call__(self) -> dict[str, int]:
        return {LAST_ACTION_KEY: self.last_action, BUMPED_KEY: int(self.env.unwrapped.bumped)}


class Proprioception(gym.Wrapper):
    """Adds :data:`LAST_ACTION_KEY` and :data:`BUMPED_KEY` to a Dict observation."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.observation_space = spaces.Dict({**env.observation_space.spaces, **proprioception_spaces()})
        self.sense = Proprioceptor(env)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        self.sense.reset()
        return {**obs, **self.sense()}, info

    def step(self, action: Any):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.sense.record(action)
        return {**obs, **self.sense()}, reward, terminated, truncated, info
