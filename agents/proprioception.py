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
(``SB3Policy``), as the wrapper does during training. :class:`LoopDetector` tells a deterministic
policy that it is in a loop it cannot leave (its input and its own motion repeat).
"""

from __future__ import annotations

import hashlib
from collections import deque
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from vgpnav_env.robot import Action, predict_pose

#: Observation keys added by :class:`Proprioception`.
LAST_ACTION_KEY, BUMPED_KEY = "last_action", "bumped"

#: Steps :class:`LoopDetector` looks back (a full turn in place takes 24); the ``escape-loops``
#: actions of ``vgpnav eval navigation`` name it.
LOOP_WINDOW = 32


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


class LoopDetector:
    """Whether a deterministic policy is in a loop it cannot leave: its input (every key, exactly)
    and its dead-reckoned pose both repeat one of the last ``window`` steps'.

    The dead-reckoned pose integrates the nominal motion of its own actions
    (:func:`~vgpnav_env.robot.predict_pose`, a blocked step counted as no motion) from the episode's
    start: what the robot knows of its motion, nothing privileged. Where both repeat, the robot
    stands where it stood and sees what it saw, so the most likely action is the one it took then
    (lost with a dead-reckoned estimate, a left and a right turn bring back the same input). Call
    :meth:`reset` at an episode's start, :meth:`visit` with the policy's input before it acts and
    :meth:`record` with the action taken.
    """

    def __init__(self, window: int = LOOP_WINDOW) -> None:
        self.seen: deque[tuple[bytes, tuple[float, ...]]] = deque(maxlen=int(window))
        self.reset()

    def reset(self) -> None:
        self.seen.clear()
        self.pose = np.zeros(3)
        self.action: int | None = None

    def record(self, action: Any) -> None:
        self.action = int(action)

    def visit(self, obs: dict[str, Any], blocked: bool) -> bool:
        """Add this step (``blocked``: the previous step's motion was) and return whether it
        repeats one of the window's."""
        if self.action is not None and not blocked:
            self.pose = predict_pose(self.pose, self.action)
        data = b"".join(np.ascontiguousarray(obs[k]).tobytes() for k in sorted(obs))
        digest = hashlib.blake2b(data).digest()
        key = (digest, tuple(np.round(self.pose, 6).tolist()))
        repeated = key in self.seen
        self.seen.append(key)
        return repeated
