"""Agents and a backbone model defined outside the package, for ``--agent MODULE:FACTORY`` and
``--backbone learned --model MODULE:FACTORY`` tests (``tests/`` is on ``sys.path``)."""

from __future__ import annotations

import os
from typing import Any

import torch

#: Episodes whose seed is this environment variable's value raise in ``Raising.act``.
RAISE_SEED = "VGPNAV_TEST_RAISE_SEED"


class BumpAndTurn:
    """Reads only the raw observation and the bump sensor: forward until a step is blocked, then a
    left turn; stops after ``budget`` steps."""

    def __init__(self, env: Any, budget: int = 25) -> None:
        self.env = env
        self.budget = budget
        self.steps = 0

    def reset(self, seed: int | None = None) -> None:
        self.steps = 0

    def act(self, obs: dict[str, Any]) -> int:
        assert set(obs) == {"rgb", "goal"}, sorted(obs)
        self.steps += 1
        if self.steps > self.budget:
            return 0
        return 2 if self.env.unwrapped.bumped else 1


class Raising(BumpAndTurn):
    """``BumpAndTurn`` that raises on its third step of the episode whose seed is ``RAISE_SEED``."""

    def reset(self, seed: int | None = None) -> None:
        super().reset(seed)
        self.seed = seed

    def act(self, obs: dict[str, Any]) -> int:
        if self.steps == 2 and str(self.seed) == os.environ.get(RAISE_SEED):
            raise RuntimeError("the agent fell over")
        return super().act(obs)


def make_turner() -> Any:
    """A factory without arguments returning an object with ``act`` only (no ``reset``, no state):
    it turns left until the step limit."""

    class Turner:
        def act(self, obs: Any) -> int:
            return 2

    return Turner()


class StillCamera(torch.nn.Module):
    """A model with the learned backbone's contract that places every image at one pose, depth 1."""

    def __init__(self) -> None:
        super().__init__()
        self.depth = torch.nn.Parameter(torch.ones(()))

    def forward(self, images: torch.Tensor) -> dict[str, torch.Tensor]:
        n, _, h, w = images.shape
        extrinsic = torch.eye(4, dtype=torch.float64)[:3].expand(n, 3, 4)
        return {
            "extrinsic": extrinsic,
            "depth": self.depth.expand(n, h, w),
            "depth_conf": torch.full((n, h, w), 2.0),
        }
