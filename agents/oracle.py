"""The oracle: the A* agent fed the TRUE pose and the ground-truth obstacle map (the upper bound).

It reads the env's true pose (``env.unwrapped.pose``), the goal of the raw observation and the
env's ground-truth map of the layout it drives in; every cell that is not free floor counts as an
obstacle, and the plan keeps to the navigable cells too (where the robot disc touches no collision
part: the inflated free floor alone passes where mesh hulls stick out past their floor cells).
Nothing here but the goal is available to a real agent.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from vgpnav_env.agents.astar import AStarAgent
from vgpnav_env.robot import Action


class OracleAgent:
    """``act(obs)`` with the true pose and the ground-truth map of ``env``'s layout."""

    def __init__(self, env: gym.Env, **agent_kwargs: Any) -> None:
        base = env.unwrapped
        if not hasattr(base, "ground_truth"):
            raise TypeError(f"the oracle needs a VGPNav point-goal env, got {type(base).__name__}")
        gt = base.ground_truth
        agent_kwargs.setdefault("robot_radius", base.robot_radius)
        agent_kwargs.setdefault("forward_step", base.forward_step)
        agent_kwargs.setdefault("turn_step_deg", float(np.degrees(base.turn_step)))
        agent_kwargs.setdefault("navigable", gt.navigable)
        agent_kwargs.setdefault("contact_arc_deg", 0.0)  # its map holds every hull: a contact is a graze
        agent_kwargs.setdefault("cost_weight", 0.0)  # an exact map needs no clearance cost: shortest paths
        self.base = base
        self.spec = gt.spec
        self.obstacles = ~np.asarray(gt.free, bool)
        self.agent = AStarAgent(**agent_kwargs)

    def reset(self, seed: int | None = None) -> None:
        self.agent.reset()

    def act(self, obs: dict[str, Any]) -> Action:
        action = self.agent.act(self.base.pose, self.obstacles, self.spec, obs["goal"])
        if self.agent.path is not None:
            self.base.set_overlay(path=self.agent.path)  # drawn by render()
        return action
