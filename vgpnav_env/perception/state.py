"""The robot's planar pose between camera frames: a small state estimator fed by actions and fixes.

Per frame the caller (the VGP-Nav wrapper) runs::

    state.predict(action, rgb)           # motion update: the commanded action, seen through pixels
    gate = state.gate()                  # where a perceived pose may lie (None: anywhere)
    result = perceiver.perceive(rgb, gate=gate)
    state.correct(base_pose(result.T_wc) if result.localized else None)
    state.estimate                       # (x, y, yaw) in W, metres and radians

:class:`PoseState` is that interface; a temporal estimator (an EKF over x, y, yaw fusing action
odometry, visual odometry and global fixes with covariances, DESIGN.md "temporal" mode) implements
it in place of :class:`OdometryState`.

:class:`OdometryState` (today's behaviour): the last fix carried forward by the robot's motion
model (:func:`vgpnav_env.robot.predict_pose`, nominal steps) for discrete actions. A forward step
after which the camera image did not change -- mean absolute grey difference of a 40x30 thumbnail
below ``stall_threshold`` levels -- was blocked and moves nothing. The odometry gate (discrete
actions, after a first fix): a perceived pose farther than ``max_distance`` m / ``max_yaw_deg``
from the prediction is rejected; since the last fix the distance grows by ``growth_m`` per forward
step and the angle by ``growth_deg`` per turn (odometry uncertainty grows with motion, not time:
turning in place does not widen the distance gate), so a drifted estimate is re-captured once the
robot moves. Before the first fix of an episode the estimate is ``fallback`` (e.g. the map
centre). Estimates are clipped to the box [``low``, ``high``].
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from vgpnav_env.perception.verify import PoseGate
from vgpnav_env.robot import FORWARD_STEP, TURN_STEP_DEG, Action, predict_pose

#: Mean absolute grey-level change (of a 40x30 thumbnail) below which a forward step was blocked.
STALL_THRESHOLD = 0.5


@dataclass(frozen=True)
class GateConfig:
    """The odometry gate: ``max_distance`` m and ``max_yaw_deg`` around the prediction right after a
    fix, growing by ``growth_m`` per forward step and ``growth_deg`` per turn since the fix."""

    max_distance: float = 0.5
    max_yaw_deg: float = 30.0
    growth_m: float = 0.1
    growth_deg: float = 5.0

    def __post_init__(self) -> None:
        if min(self.max_distance, self.max_yaw_deg, self.growth_m, self.growth_deg) <= 0:
            raise ValueError(
                "motion gate (max_distance m, max_yaw_deg, growth m per forward step, growth deg per "
                f"turn) must all be positive, got {tuple(vars(self).values())}"
            )


class PoseState(Protocol):
    """A planar pose estimator between frames (see the module docstring)."""

    def reset(self, rgb: NDArray[np.uint8], fallback: ArrayLike) -> None:
        """A new episode: no fix yet, ``fallback`` (x, y, yaw) until the first one; ``rgb`` is the
        first camera image."""

    def predict(self, action: int | NDArray | None, rgb: NDArray[np.uint8]) -> None:
        """Motion update for the commanded ``action``, with the camera image taken after it."""

    def gate(self) -> PoseGate | None:
        """Where this frame's perceived pose must lie to be accepted (None: no constraint)."""

    def correct(self, measured: NDArray[np.float64] | None) -> None:
        """Measurement update with the perceived pose (x, y, yaw), or None when perception is lost."""

    @property
    def estimate(self) -> NDArray[np.float64]:
        """The current (x, y, yaw) estimate in W."""

    @property
    def localized(self) -> bool:
        """Whether the last :meth:`correct` had a perceived pose."""


def _thumbnail(rgb: NDArray[np.uint8]) -> NDArray[np.float32]:
    """A 40x30 grey thumbnail (float grey levels) for detecting a blocked step from pixels."""
    grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
    return cv2.resize(grey, (40, 30), interpolation=cv2.INTER_AREA).astype(np.float32)


class OdometryState:
    """Dead reckoning between fixes with pixel stall detection and the odometry gate.

    ``discrete``: the actions are :class:`~vgpnav_env.robot.Action` values moving
    ``forward_step`` m / ``turn_step`` rad (else continuous commands: no dead reckoning, no gate).
    ``gate``: a :class:`GateConfig`, or None for no gate.
    """

    def __init__(
        self,
        low: ArrayLike,
        high: ArrayLike,
        *,
        discrete: bool = True,
        forward_step: float = FORWARD_STEP,
        turn_step: float = float(np.radians(TURN_STEP_DEG)),
        gate: GateConfig | None = GateConfig(),
        stall_threshold: float = STALL_THRESHOLD,
    ) -> None:
        if stall_threshold < 0:
            raise ValueError(f"stall_threshold must be >= 0 grey levels (0 = off), got {stall_threshold}")
        self.low, self.high = np.asarray(low), np.asarray(high)
        self.discrete = bool(discrete)
        self.forward_step, self.turn_step = float(forward_step), float(turn_step)
        self.gate_config = gate
        self.stall_threshold = float(stall_threshold)
        self._estimate = np.zeros(3)
        self._fallback = np.zeros(3)
        self._predicted: NDArray[np.float64] | None = None
        self._have_fix = False
        self._localized = False
        self._moves_since_fix = np.zeros(2)  # forward steps, turns
        self._thumbnail: NDArray[np.float32] | None = None

    @property
    def estimate(self) -> NDArray[np.float64]:
        return self._estimate

    @property
    def localized(self) -> bool:
        return self._localized

    def reset(self, rgb: NDArray[np.uint8], fallback: ArrayLike) -> None:
        self._estimate = np.zeros(3)
        self._fallback = np.asarray(fallback, float)
        self._predicted = None
        self._have_fix = False
        self._localized = False
        self._moves_since_fix = np.zeros(2)
        self._thumbnail = _thumbnail(rgb)

    def predict(self, action: int | NDArray | None, rgb: NDArray[np.uint8]) -> None:
        thumbnail = _thumbnail(rgb)
        stalled = float(np.abs(thumbnail - self._thumbnail).mean()) < self.stall_threshold
        self._thumbnail = thumbnail
        if not self.discrete or action is None:
            self._predicted = self._estimate.copy() if self._have_fix else None
            return
        action = Action(int(action))
        if stalled and action == Action.FORWARD:
            action = Action.STOP  # the image did not change: the step was blocked, the robot stayed
        if self._have_fix:
            self._predicted = predict_pose(self._estimate, action, self.forward_step, self.turn_step)
        self._moves_since_fix += (action == Action.FORWARD, action in (Action.TURN_LEFT, Action.TURN_RIGHT))

    def gate(self) -> PoseGate | None:
        cfg = self.gate_config
        if self._predicted is None or cfg is None or not self.discrete:
            return None
        forward, turns = self._moves_since_fix
        return PoseGate(
            self._predicted,
            cfg.max_distance + cfg.growth_m * forward,
            float(np.radians(cfg.max_yaw_deg + cfg.growth_deg * turns)),
        )

    def correct(self, measured: NDArray[np.float64] | None) -> None:
        self._localized = measured is not None
        if measured is not None:
            estimate = np.asarray(measured, float)
            self._have_fix = True
            self._moves_since_fix = np.zeros(2)
        elif self._predicted is not None:
            estimate = self._predicted
        else:  # no fix yet in this episode
            estimate = self._fallback
        self._estimate = np.clip(estimate, self.low, self.high)
        self._predicted = None
