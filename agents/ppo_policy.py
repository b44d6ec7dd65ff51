"""The torch parts of the PPO recipe (imported only when training or loading a policy).

Module level, so that saved models name :class:`NavigationExtractor` by reference.
"""

from __future__ import annotations

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from vgpnav_env.agents.proprioception import BUMPED_KEY, LAST_ACTION_KEY

#: Episode measures logged to TensorBoard (means over SB3's last 100 episodes).
LOGGED = {"success": "rollout/success_rate", "spl": "rollout/spl"}


def single_thread() -> None:
    """Run torch on one thread: the small convolutions of a policy gain nothing from more, and on a
    loaded machine multi-threaded ones stall (measured: 70 ms per batch-1 convolution at load 16,
    the process getting 67 CPU-s in 349 s wall for 1024 PPO steps)."""
    torch.set_num_threads(1)


class NavigationExtractor(BaseFeaturesExtractor):
    """Features of a navigation observation (``vgpnav_env.wrappers.navigation_space``).

    The map crop (1, S, S; SB3 scales it to [0, 1]), stacked with the planner's ``path`` channel
    when the space has one (``agents.guidance``), through 3 strided convolutions to
    ``map_features``; the goal as (log(1 + distance m), cos, sin of the bearing), the same of the
    planner's ``waypoint`` when guided, the localized flag and, when the space has them
    (``agents.proprioception``), the previous action (one-hot) and the bump flag to
    ``goal_features``; concatenated. ``pose`` (world coordinates, scene specific) is ignored.
    """

    def __init__(
        self, observation_space: spaces.Dict, map_features: int = 128, goal_features: int = 64
    ) -> None:
        super().__init__(observation_space, map_features + goal_features)
        self.guided = "path" in observation_space.spaces
        self.proprioceptive = BUMPED_KEY in observation_space.spaces
        shape = observation_space["map"].shape
        shape = (shape[0] * (2 if self.guided else 1), *shape[1:])
        self.cnn = nn.Sequential(
            nn.Conv2d(shape[0], 16, 5, stride=2, padding=2),
            nn.ReLU(),
            nn.Conv2d(16, 32, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.Conv2d(32, 32, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.Flatten(),
        )
        with torch.no_grad():
            n = self.cnn(torch.zeros(1, *shape)).shape[1]
        self.map_fc = nn.Sequential(nn.Linear(n, map_features), nn.ReLU())
        n_goal = 7 if self.guided else 4
        if self.proprioceptive:
            n_goal += observation_space[LAST_ACTION_KEY].n + 1
        self.goal_fc = nn.Sequential(nn.Linear(n_goal, goal_features), nn.ReLU())

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        goal = obs["goal_rel"]
        localized = obs["localized"].reshape(len(goal), -1)[:, -1:]  # SB3's one-hot (B, 2) -> flag
        polar = [obs["goal_rel"], obs["waypoint"]] if self.guided else [obs["goal_rel"]]
        parts = [torch.cat([torch.log1p(p[:, :1]), torch.cos(p[:, 1:2]), torch.sin(p[:, 1:2])], 1)
                 for p in polar]  # fmt: skip
        if self.proprioceptive:  # SB3 one-hot encodes both: the action as is, the bump as a flag
            bumped = obs[BUMPED_KEY].reshape(len(goal), -1)[:, -1:]
            parts += [obs[LAST_ACTION_KEY].reshape(len(goal), -1), bumped]
        g = torch.cat([*parts, localized], 1)
        grid = torch.cat([obs["map"], obs["path"]], 1) if self.guided else obs["map"]
        return torch.cat([self.map_fc(self.cnn(grid)), self.goal_fc(g)], dim=1)


class SuccessLogger(BaseCallback):
    """Logs :data:`LOGGED` (from the monitor's episode infos) at the end of every rollout."""

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        episodes = [e for e in self.model.ep_info_buffer if "success" in e]
        if episodes:
            for key, name in LOGGED.items():
                self.logger.record(name, float(np.mean([float(e[key]) for e in episodes])))


class GoalCurriculum(BaseCallback):
    """Goal-distance curriculum: episodes start with goals at most ``start`` m (geodesic) away;
    when ``threshold`` of the last ``window`` episodes sampled at the current limit succeed, the
    limit grows by ``step`` m, up to ``stop`` m (the env's default range). Logs
    ``curriculum/max_geodesic``. Sets the range through the envs' ``set_goal_range``."""

    def __init__(
        self,
        start: float = 2.0,
        step: float = 1.0,
        stop: float = 10.0,
        threshold: float = 0.5,
        window: int = 50,
        min_geodesic: float = 1.0,
    ) -> None:
        super().__init__()
        self.start, self.step, self.stop = float(start), float(step), float(stop)
        self.threshold, self.window, self.min_geodesic = float(threshold), int(window), float(min_geodesic)
        self.limit = self.start
        self.results: list[float] = []

    def _set(self) -> None:
        self.training_env.env_method("set_goal_range", self.min_geodesic, self.limit)
        self.results = []

    def _on_training_start(self) -> None:
        self._set()

    def _on_step(self) -> bool:
        # Episodes that ended in this step; the first ones after a change may have started before it.
        for info in self.locals.get("infos", []):
            if "episode" in info:
                self.results.append(float(info.get("success", 0.0)))
        recent = self.results[-self.window :]
        if self.limit < self.stop and len(recent) >= self.window and np.mean(recent) >= self.threshold:
            self.limit = min(self.limit + self.step, self.stop)
            self._set()
        return True

    def _on_rollout_end(self) -> None:
        self.logger.record("curriculum/max_geodesic", self.limit)


def behaviour_clone(
    model,
    observations: dict[str, np.ndarray],
    actions: np.ndarray,
    epochs: int = 8,
    batch: int = 128,
    lr: float = 1e-3,
) -> float:
    """Fit ``model``'s policy (an SB3 PPO) to demonstrated ``actions`` by maximum likelihood (the
    value head is left to PPO); returns the last epoch's mean negative log-likelihood."""
    policy = model.policy
    optimizer = torch.optim.Adam(policy.parameters(), lr=lr)
    obs, _ = policy.obs_to_tensor(observations)
    acts = torch.as_tensor(actions, dtype=torch.long)
    generator = torch.Generator().manual_seed(0)
    loss_value = float("nan")
    for _ in range(epochs):
        losses = []
        for idx in torch.randperm(len(acts), generator=generator).split(batch):
            _, log_prob, _ = policy.evaluate_actions({k: v[idx] for k, v in obs.items()}, acts[idx])
            loss = -log_prob.mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            losses.append(loss.item())
        loss_value = float(np.mean(losses))
    return loss_value
