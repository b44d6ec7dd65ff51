"""The robot's planar pose between camera frames: a small state estimator fed by actions and fixes.

Per frame the caller (the VGP-Nav wrapper) runs::

    state.predict(action, rgb, bumped)   # motion update: the commanded action, its bump, the pixels
    gate = state.gate()                  # where a perceived pose may lie (None: anywhere)
    result = perceiver.perceive(rgb, gate=gate, prior=state.prior())
    state.correct(None if result.measurement is None else base_pose(result.measurement))
    state.estimate                       # (x, y, yaw) in W, metres and radians

:class:`PoseState` is that interface. :class:`EKFState` (the "temporal" perception mode): an EKF
over x, y, yaw fusing action odometry and global fixes with their covariances, Mahalanobis gating,
kidnapping detection, and a :meth:`~PoseState.tracking_pose` around which the perceiver chooses
references while the estimate is certain.

:class:`OdometryState` (today's behaviour): the last fix carried forward by the robot's motion
model (:func:`vgpnav_env.robot.predict_pose`, nominal steps) for discrete actions. A blocked
forward step moves nothing. Blocked: the robot's bump sensor (``bumped``, the env's
:attr:`~vgpnav_env.envs.pointgoal.PointGoalEnv.bumped`; the env stops a blocked motion at its
last collision-free pose, anywhere along the step) or, without one (``bumped=None``), a camera
image that did not change -- mean absolute grey difference of a 40x30 thumbnail below
``stall_threshold`` levels (a push into a wall that moves a few millimetres can change it more:
the bump sensor is the reliable detector). The odometry gate (discrete actions, after a first
fix): a perceived pose farther than ``max_distance`` m / ``max_yaw_deg`` from the prediction is
rejected; since the last fix the distance grows by ``growth_m`` per forward step and the angle by
``growth_deg`` per turn (odometry uncertainty grows with motion, not time: turning in place does
not widen the distance gate), so a drifted estimate is re-captured once the robot moves. Before
the first fix of an episode the estimate is ``fallback`` (e.g. the map centre). Estimates are
clipped to the box [``low``, ``high``].
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from vgpnav_env.geometry import wrap_angle
from vgpnav_env.perception.verify import PoseGate
from vgpnav_env.robot import FORWARD_STEP, TURN_STEP_DEG, Action, predict_pose

logger = logging.getLogger(__name__)

#: Mean absolute grey-level change (of a 40x30 thumbnail) below which a forward step was blocked.
STALL_THRESHOLD = 0.5
#: What a pose state did with a frame's measurement -> meaning (reports define their labels from it).
FIX_OUTCOMES: dict[str, str] = {
    "none": "no perceived pose: the estimate was carried by odometry",
    "accepted": "the perceived pose agreed with the estimate and corrected it",
    "rejected": "the perceived pose contradicted the estimate (outside its gate) and was ignored",
    "reset": "the estimate was set to the perceived pose (first confirmed fix, or a detected kidnapping)",
    "unconfirmed": "a perceived pose before the first estimate, not yet confirmed by a consistent one "
    "from another view",
}


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

    def predict(
        self, action: int | NDArray | None, rgb: NDArray[np.uint8], bumped: bool | None = None
    ) -> None:
        """Motion update for the commanded ``action``, with the camera image taken after it and the
        bump sensor's reading during it (None: no bump sensor, blocked steps are seen in pixels)."""

    def gate(self) -> PoseGate | None:
        """Where this frame's perceived pose must lie to be accepted (None: no constraint)."""

    def correct(self, measured: NDArray[np.float64] | None, score: float = 0.0) -> None:
        """Measurement update with the perceived pose (x, y, yaw), or None when perception is lost;
        ``score``: how strongly the images confirm it (the verifier's
        :attr:`~vgpnav_env.perception.verify.Verdict.score`, 0 = unknown)."""

    @property
    def estimate(self) -> NDArray[np.float64]:
        """The current (x, y, yaw) estimate in W."""

    @property
    def localized(self) -> bool:
        """Whether the last :meth:`correct` took in a perceived pose."""

    @property
    def fix(self) -> str:
        """What the last :meth:`correct` did with its measurement (:data:`FIX_OUTCOMES`)."""

    @property
    def blocked(self) -> bool:
        """Whether the last :meth:`predict`'s forward step was blocked (its bump, or without a bump
        sensor an unchanged image), also before the first fix, when :attr:`estimate` does not move."""

    @property
    def covariance(self) -> NDArray[np.float64] | None:
        """The estimate's 3x3 covariance over (x, y, yaw) (m^2, m rad, rad^2); None: not kept."""

    @property
    def has_estimate(self) -> bool:
        """Whether there is an estimate at all (False before the first fix of an episode:
        :attr:`estimate` is then the fallback placeholder)."""

    def tracking_pose(self) -> NDArray[np.float64] | None:
        """The predicted (x, y, yaw) to choose this frame's references around (tracking), or None:
        global retrieval (relocalization). Call after :meth:`predict`."""

    def prior(self) -> PoseGate | None:
        """Where the estimate confidently expects the robot this frame (the perceiver's ``prior``: a
        pose inside needs less from the images, a verified one outside is "inconsistent motion"
        but still reaches :meth:`correct`), or None. Call after :meth:`predict`."""


def _thumbnail(rgb: NDArray[np.uint8]) -> NDArray[np.float32]:
    """A 40x30 grey thumbnail (float grey levels) for detecting a blocked step from pixels."""
    grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
    return cv2.resize(grey, (40, 30), interpolation=cv2.INTER_AREA).astype(np.float32)


class _StallDetector:
    """Whether the camera image stayed the same since the previous one (mean absolute grey change of
    the thumbnails below ``threshold`` levels): after a forward step, the step was blocked."""

    def __init__(self, threshold: float) -> None:
        if threshold < 0:
            raise ValueError(f"stall_threshold must be >= 0 grey levels (0 = off), got {threshold}")
        self.threshold = float(threshold)
        self._thumbnail: NDArray[np.float32] | None = None

    def reset(self, rgb: NDArray[np.uint8]) -> None:
        self._thumbnail = _thumbnail(rgb)

    def stalled(self, rgb: NDArray[np.uint8]) -> bool:
        thumbnail = _thumbnail(rgb)
        stalled = float(np.abs(thumbnail - self._thumbnail).mean()) < self.threshold
        self._thumbnail = thumbnail
        return stalled


def _blocked(action: int | NDArray | None, stalled: bool, bumped: bool | None) -> bool:
    """Whether a forward ``action`` was blocked: it ``bumped`` (the bump sensor), or without one
    (None) its image ``stalled``. Other actions are never blocked (the hull is a disc)."""
    if action is None or np.ndim(action) != 0 or Action(int(action)) != Action.FORWARD:
        return False
    return stalled if bumped is None else bool(bumped)


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
        self.low, self.high = np.asarray(low), np.asarray(high)
        self.discrete = bool(discrete)
        self.forward_step, self.turn_step = float(forward_step), float(turn_step)
        self.gate_config = gate
        self._estimate = np.zeros(3)
        self._fallback = np.zeros(3)
        self._predicted: NDArray[np.float64] | None = None
        self._have_fix = False
        self._localized = False
        self._moves_since_fix = np.zeros(2)  # forward steps, turns
        self._stall = _StallDetector(stall_threshold)
        self._blocked = False

    @property
    def estimate(self) -> NDArray[np.float64]:
        return self._estimate

    @property
    def localized(self) -> bool:
        return self._localized

    @property
    def fix(self) -> str:
        return "accepted" if self._localized else "none"

    @property
    def blocked(self) -> bool:
        return self._blocked

    @property
    def covariance(self) -> None:
        return None

    @property
    def has_estimate(self) -> bool:
        return self._have_fix

    def tracking_pose(self) -> None:
        return None

    def prior(self) -> None:
        return None

    def reset(self, rgb: NDArray[np.uint8], fallback: ArrayLike) -> None:
        self._estimate = np.zeros(3)
        self._fallback = np.asarray(fallback, float)
        self._predicted = None
        self._have_fix = False
        self._localized = False
        self._moves_since_fix = np.zeros(2)
        self._stall.reset(rgb)
        self._blocked = False

    def predict(
        self, action: int | NDArray | None, rgb: NDArray[np.uint8], bumped: bool | None = None
    ) -> None:
        self._blocked = _blocked(action, self._stall.stalled(rgb), bumped)
        if not self.discrete or action is None:
            self._predicted = self._estimate.copy() if self._have_fix else None
            return
        action = Action.STOP if self._blocked else Action(int(action))
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

    def correct(self, measured: NDArray[np.float64] | None, score: float = 0.0) -> None:
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


@dataclass(frozen=True)
class EKFConfig:
    """Noise model and thresholds of :class:`EKFState` (metres, degrees).

    Process (action odometry, per action): ``forward_sigma`` along and ``lateral_sigma`` across the
    heading per forward step, ``turn_sigma_deg`` per turn; a continuous command adds
    ``continuous_sigma`` / ``continuous_sigma_deg`` per step. Measurement (a global VGP-Nav fix):
    ``fix_sigma`` per horizontal axis, ``fix_sigma_deg`` in yaw. A fix whose squared Mahalanobis
    distance to the prediction exceeds ``gate_chi2`` (3 degrees of freedom; 14.2 = 99.7 %) is
    rejected. Consecutive rejected fixes that agree with each other (moved by the same odometry)
    reset the estimate to the last of them -- the robot was moved, or the estimate had drifted
    away -- once they are at least ``kidnap_fixes`` and outnumber the estimate's support: the fixes
    that set it and those it accepted since, counted up to ``max_support`` (a place that looks like
    another one gives runs of consistent wrong fixes; they must outweigh the estimate's own
    support, and an accepted fix ends the run). Fixes within ``drift_m`` of the estimate need only
    ``kidnap_fixes``: the estimate drifted (e.g. a blocked step the pixels did not show), it was not
    carried away. Either way the run must hold fixes of two views: its first taken at least
    ``init_view_m`` of travel (a blocked step counts none) or ``init_view_deg`` of net turning
    before its last (by the odometry): fixes of the spot the robot stands on may share one error.
    The first
    estimate of an episode likewise needs ``init_fixes`` consistent fixes, the earliest of them
    taken at least ``init_view_m`` of travel or ``init_view_deg`` of turning before the last (by
    the odometry): a single wrong first fix, or several of one view, would otherwise start the
    episode at the wrong place; a fix whose verifier score reaches ``init_score`` starts it alone.
    The estimate's ``prior`` (:meth:`EKFState.prior`: the region of the fixes it would accept)
    goes to the perceiver while it is within ``prior_max_m`` and ``prior_max_deg``: inside it, a
    pose needs less from the images, and a rival there beats the same view in an identical ward
    (:func:`~vgpnav_env.perception.verify.verify_pose`, :func:`~vgpnav_env.perception.verify.
    prior_hypothesis`). The position bound stays under a gross error (0.5 m); the yaw bound may
    not: a pose's rotation comes from the images (the pairs' rotations, verified to 2 px), the
    prior's heading only keeps out views facing elsewhere. Tracking (references around the
    prediction) while the position standard deviation (largest axis) is at most
    ``track_max_sigma`` and the yaw's at most ``track_max_sigma_deg``; beyond, global retrieval
    relocalizes. A tracked frame that perceived no pose hands the next frame to global retrieval
    (then tracking again, alternating while lost): each frame runs one localization attempt, never
    a tracking attempt and a global one.
    """

    forward_sigma: float = 0.03
    lateral_sigma: float = 0.015
    turn_sigma_deg: float = 1.5
    continuous_sigma: float = 0.05
    continuous_sigma_deg: float = 5.0
    fix_sigma: float = 0.05
    fix_sigma_deg: float = 2.0
    gate_chi2: float = 14.2
    kidnap_fixes: int = 3
    init_fixes: int = 2
    init_view_m: float = 0.25
    init_view_deg: float = 30.0
    init_score: float = 0.9
    max_support: int = 8
    drift_m: float = 0.5
    track_max_sigma: float = 0.5
    track_max_sigma_deg: float = 20.0
    prior_max_m: float = 0.4
    prior_max_deg: float = 25.0

    def __post_init__(self) -> None:
        values = (self.forward_sigma, self.lateral_sigma, self.turn_sigma_deg, self.continuous_sigma,
                  self.continuous_sigma_deg, self.fix_sigma, self.fix_sigma_deg, self.gate_chi2,
                  self.track_max_sigma, self.track_max_sigma_deg, self.drift_m, self.init_view_m,
                  self.init_view_deg, self.init_score, self.prior_max_m, self.prior_max_deg)  # fmt: skip
        if min(values) <= 0 or min(self.kidnap_fixes, self.init_fixes, self.max_support) < 1:
            raise ValueError(
                f"EKF noise and thresholds must be positive, kidnap_fixes, init_fixes and "
                f"max_support >= 1, got {self}"
            )

    @property
    def fix_covariance(self) -> NDArray[np.float64]:
        """R: the 3x3 covariance of a global fix."""
        return np.diag([self.fix_sigma**2, self.fix_sigma**2, np.radians(self.fix_sigma_deg) ** 2])


#: How many perceived poses before the first estimate :class:`EKFState` keeps (the latest).
CANDIDATES = 30


@dataclass
class _Candidate:
    """A perceived pose before the first estimate, carried by the odometry since: ``pose`` (x, y,
    yaw) and covariance ``P`` now, ``moved`` metres travelled and ``turned`` radians (signed net
    rotation) since it was perceived."""

    pose: NDArray[np.float64]
    P: NDArray[np.float64]
    moved: float = 0.0
    turned: float = 0.0


class EKFState:
    """An extended Kalman filter over the planar pose (x, y, yaw) in W (the "temporal" mode).

    Process model: the robot's motion model (:func:`~vgpnav_env.robot.predict_pose`) for the
    commanded discrete action, noise per :class:`EKFConfig`; a blocked forward step (bump sensor,
    else an unchanged image) moved anywhere from nothing to a full step: half a step, the variance
    of a uniform over the step added (a fix where the robot stayed is then within the gate), or
    nothing when its image did not change either. Measurements: perceived poses
    with covariance ``config.fix_covariance``, Mahalanobis-gated (no :class:`PoseGate`: the perceiver
    is not constrained, so that fixes contradicting the estimate still reach :meth:`correct` for
    kidnapping detection). Before the first estimate (``config.init_fixes`` consistent fixes from
    views at least ``config.init_view_m`` / ``init_view_deg`` apart, or one fix scoring
    ``config.init_score``) the estimate is the fallback placeholder with an unbounded covariance.
    Estimates are clipped to [``low``, ``high``].
    """

    def __init__(
        self,
        low: ArrayLike,
        high: ArrayLike,
        *,
        discrete: bool = True,
        forward_step: float = FORWARD_STEP,
        turn_step: float = float(np.radians(TURN_STEP_DEG)),
        config: EKFConfig | None = None,
        stall_threshold: float = STALL_THRESHOLD,
    ) -> None:
        self.low, self.high = np.asarray(low, float), np.asarray(high, float)
        self.discrete = bool(discrete)
        self.forward_step, self.turn_step = float(forward_step), float(turn_step)
        self.config = config or EKFConfig()
        self._stall = _StallDetector(stall_threshold)
        self._blocked = False
        self._x = np.zeros(3)
        self._P = np.full((3, 3), np.inf)
        self._have_fix = False
        self._fix = "none"
        self._candidate: NDArray[np.float64] | None = None  # the last rejected fix, moved by odometry
        self._candidate_P = np.zeros((3, 3))
        self._candidate_count = 0
        self._run = np.zeros(2)  # travel (m) and net turn (rad) since the run's first rejected fix
        self._support = 0  # the fixes that set the estimate and those accepted since (capped)
        self._pool: list[_Candidate] = []  # the fixes before the first estimate (the latest)
        self._track = False  # whether this frame tracks (decided by the motion update)

    @property
    def estimate(self) -> NDArray[np.float64]:
        return np.clip(self._x, self.low, self.high)

    @property
    def has_estimate(self) -> bool:
        return self._have_fix

    @property
    def covariance(self) -> NDArray[np.float64]:
        return self._P.copy()

    @property
    def localized(self) -> bool:
        return self._fix in ("accepted", "reset")

    @property
    def fix(self) -> str:
        return self._fix

    @property
    def blocked(self) -> bool:
        return self._blocked

    def reset(self, rgb: NDArray[np.uint8], fallback: ArrayLike) -> None:
        self._stall.reset(rgb)
        self._blocked = False
        self._x = np.asarray(fallback, float).copy()
        self._P = np.full((3, 3), np.inf)
        self._have_fix = False
        self._fix = "none"
        self._candidate, self._candidate_count = None, 0
        self._run = np.zeros(2)
        self._support = 0
        self._pool = []
        self._track = False

    def _motion(self, action: int | NDArray | None, blocked: bool, stalled: bool):
        """The commanded ``action`` as a motion (forward m, left m, yaw rad) in the robot frame with
        its 3x3 covariance; None: a continuous command of unknown extent. A ``blocked`` forward step
        ended anywhere along the step (the env stops it at the last collision-free pose): half a
        step with the variance of a uniform over the step added, or nothing when the image also
        ``stalled`` (a push against what blocked it)."""
        cfg = self.config
        if not self.discrete or action is None:
            return None
        action = Action(int(action))
        if action == Action.FORWARD:
            if blocked and stalled:
                return np.zeros(3), np.zeros((3, 3))
            length, variance = self.forward_step, cfg.forward_sigma**2
            if blocked:
                length, variance = 0.5 * length, variance + length**2 / 12.0
            return np.array([length, 0.0, 0.0]), np.diag([variance, cfg.lateral_sigma**2, 0.0])
        if action in (Action.TURN_LEFT, Action.TURN_RIGHT):
            yaw = self.turn_step if action == Action.TURN_LEFT else -self.turn_step
            return np.array([0.0, 0.0, yaw]), np.diag([0.0, 0.0, np.radians(cfg.turn_sigma_deg) ** 2])
        return np.zeros(3), np.zeros((3, 3))

    def predict(
        self, action: int | NDArray | None, rgb: NDArray[np.uint8], bumped: bool | None = None
    ) -> None:
        stalled = self._stall.stalled(rgb)
        self._blocked = _blocked(action, stalled, bumped)
        motion = self._motion(action, self._blocked, stalled)
        if motion is None:
            cfg = self.config
            Q = np.diag([cfg.continuous_sigma**2] * 2 + [np.radians(cfg.continuous_sigma_deg) ** 2])
            if self._have_fix:
                self._P = self._P + Q
            if self._candidate is not None:
                self._candidate_P = self._candidate_P + Q
            for c in self._pool:
                c.P = c.P + Q
            self._decide_tracking()
            return
        # a blocked step may have moved nothing: no travel toward another view
        self.predict_odometry(*motion, travelled=0.0 if self._blocked else None)

    def _decide_tracking(self) -> None:
        """After a motion update: whether the new frame tracks -- the estimate is certain enough,
        and the previous frame was not a tracking attempt that perceived no pose (see
        :class:`EKFConfig`)."""
        failed = self._track and self._fix == "none"
        self._track = self._have_fix and not _too_uncertain(self._P, self.config) and not failed

    def odometry_covariance(self, motion: ArrayLike) -> NDArray[np.float64]:
        """The 3x3 covariance of measured odometry ``motion`` (forward m, left m, yaw rad): that of
        the equivalent number of nominal steps, variance ``forward_sigma^2`` / ``lateral_sigma^2``
        per ``forward_step`` of distance and ``turn_sigma_deg^2`` per ``turn_step`` of rotation."""
        cfg, d = self.config, np.asarray(motion, float)
        steps = np.hypot(d[0], d[1]) / self.forward_step
        turns = abs(d[2]) / self.turn_step
        return np.diag([cfg.forward_sigma**2 * steps, cfg.lateral_sigma**2 * steps,
                        np.radians(cfg.turn_sigma_deg) ** 2 * turns])  # fmt: skip

    def predict_odometry(
        self, motion: ArrayLike, covariance: ArrayLike | None = None, travelled: float | None = None
    ) -> None:
        """Motion update by measured odometry instead of an action: ``motion`` (forward m, left m,
        yaw rad) in the robot frame of the previous pose (e.g. wheel odometry over a query run's
        continuous motion, possibly refined by visual odometry) with its 3x3 ``covariance``
        (default :meth:`odometry_covariance`). ``travelled``: the distance surely travelled, toward
        fixes from another view (default: the motion's; 0 for a blocked step)."""
        d = np.asarray(motion, float)
        Q = self.odometry_covariance(d) if covariance is None else np.asarray(covariance, float)
        travelled = float(np.hypot(d[0], d[1])) if travelled is None else float(travelled)
        if self._have_fix:
            self._x, self._P = self._odometry(self._x, self._P, d, Q)
        if self._candidate is not None:
            self._candidate, self._candidate_P = self._odometry(self._candidate, self._candidate_P, d, Q)
            self._run += (travelled, d[2])
        for c in self._pool:
            c.pose, c.P = self._odometry(c.pose, c.P, d, Q)
            c.moved, c.turned = c.moved + travelled, c.turned + float(d[2])
        self._decide_tracking()

    def _odometry(self, x: NDArray[np.float64], P: NDArray[np.float64], d: NDArray[np.float64], Q_d):
        c, s = np.cos(x[2]), np.sin(x[2])
        G = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # motion frame -> W
        x_new = np.r_[x[:2] + G[:2, :2] @ d[:2], wrap_angle(x[2] + d[2])]
        F = np.eye(3)
        F[:2, 2] = [-s * d[0] - c * d[1], c * d[0] - s * d[1]]
        return x_new, F @ P @ F.T + G @ Q_d @ G.T

    def gate(self) -> None:
        return None

    def tracking_pose(self) -> NDArray[np.float64] | None:
        return self.estimate if self._track else None

    def prior(self) -> PoseGate | None:
        """Where the estimate confidently expects the robot: the fixes :meth:`correct` would accept
        (``gate_chi2`` over the estimate's and a fix's covariance) as a distance and a yaw bound
        around the estimate, when these are within ``prior_max_m`` / ``prior_max_deg`` -- its
        position never wider than a gross error -- else None. Call after :meth:`predict`."""
        cfg = self.config
        if not self._have_fix:
            return None
        S = self._P + cfg.fix_covariance
        distance = float(np.sqrt(cfg.gate_chi2 * np.linalg.eigvalsh(S[:2, :2]).max()))
        yaw = float(np.sqrt(cfg.gate_chi2 * S[2, 2]))
        if distance > cfg.prior_max_m or yaw > np.radians(cfg.prior_max_deg):
            return None
        return PoseGate(self.estimate, distance, yaw)

    def mahalanobis2(self, measured: ArrayLike) -> float:
        """Squared Mahalanobis distance of a perceived pose from the estimate (inf before a fix)."""
        if not self._have_fix:
            return float("inf")
        return _mahalanobis2(measured, self._x, self._P + self.config.fix_covariance)

    def correct(self, measured: NDArray[np.float64] | None, score: float = 0.0) -> None:
        cfg = self.config
        if measured is None:
            self._fix = "none"
            return
        z = np.asarray(measured, float)
        R = cfg.fix_covariance
        if self._have_fix and self.mahalanobis2(z) <= cfg.gate_chi2:
            S = self._P + R
            K = self._P @ np.linalg.inv(S)
            self._x = self._x + K @ _innovation(z, self._x)
            self._x[2] = wrap_angle(self._x[2])
            I_K = np.eye(3) - K
            self._P = I_K @ self._P @ I_K.T + K @ R @ K.T  # Joseph form: stays symmetric positive
            self._fix = "accepted"
            self._candidate, self._candidate_count = None, 0
            self._support = min(self._support + 1, self.config.max_support)
            return
        if not self._have_fix:
            self._first_estimate(z, score)
            return
        agrees = (
            self._candidate is not None
            and _mahalanobis2(z, self._candidate, self._candidate_P + R) <= cfg.gate_chi2
        )
        self._candidate_count = self._candidate_count + 1 if agrees else 1
        if not agrees:
            self._run = np.zeros(2)
        self._candidate, self._candidate_P = z, R.copy()
        self._fix = "rejected"
        drifted = float(np.linalg.norm(z[:2] - self._x[:2])) <= cfg.drift_m
        needed = cfg.kidnap_fixes if drifted else max(cfg.kidnap_fixes, self._support + 1)
        if self._candidate_count >= needed and _other_view(*self._run, cfg):
            logger.debug("kidnapping: %d consistent fixes off the estimate", self._candidate_count)
            self._take(z)

    def _first_estimate(self, z: NDArray[np.float64], score: float) -> None:
        """Before the first estimate: start it at the fix ``z`` when its ``score`` is strong, or when
        ``init_fixes`` kept fixes (``z`` included) agree with it under the odometry and one of them
        is from another view (see :class:`EKFConfig`); else keep ``z`` (the latest
        :data:`CANDIDATES`). Kept fixes whose odometry became too uncertain to confirm are dropped."""
        cfg, R = self.config, self.config.fix_covariance
        self._pool = [c for c in self._pool if not _too_uncertain(c.P, cfg)]
        agreeing = [c for c in self._pool if _mahalanobis2(z, c.pose, c.P + R) <= cfg.gate_chi2]
        other_view = any(_other_view(c.moved, c.turned, cfg) for c in agreeing)
        self._fix = "unconfirmed"
        if score >= cfg.init_score or (other_view and len(agreeing) + 1 >= cfg.init_fixes):
            self._candidate_count = len(agreeing) + 1
            self._take(z)
            self._pool = []
            return
        self._pool = [*self._pool, _Candidate(z.copy(), R.copy())][-CANDIDATES:]

    def _take(self, z: NDArray[np.float64]) -> None:
        """Set the estimate to the fix ``z`` (first estimate or relocalization); the consistent
        fixes that led to it are its support."""
        self._x, self._P = z.copy(), self.config.fix_covariance.copy()
        self._have_fix = True
        self._fix = "reset"
        self._support = min(self._candidate_count, self.config.max_support)
        self._candidate, self._candidate_count = None, 0


def _other_view(travelled: float, turned: float, cfg: EKFConfig) -> bool:
    """Whether a fix perceived ``travelled`` metres and ``turned`` radians (net, signed) of odometry
    ago is from another view than the latest: at least ``cfg.init_view_m`` or ``cfg.init_view_deg``
    (several fixes of one view may share one error: an aliased place seen from where the robot
    stands)."""
    return travelled >= cfg.init_view_m or abs(turned) >= np.radians(cfg.init_view_deg)


def _too_uncertain(P: NDArray[np.float64], cfg: EKFConfig) -> bool:
    """Whether covariance ``P`` is beyond tracking: position standard deviation (largest axis) above
    ``cfg.track_max_sigma`` or the yaw's above ``cfg.track_max_sigma_deg``."""
    position_sigma = float(np.sqrt(np.linalg.eigvalsh(P[:2, :2]).max()))
    yaw_sigma = float(np.degrees(np.sqrt(P[2, 2])))
    return position_sigma > cfg.track_max_sigma or yaw_sigma > cfg.track_max_sigma_deg


def _innovation(z: ArrayLike, x: NDArray[np.float64]) -> NDArray[np.float64]:
    d = np.asarray(z, float) - x
    d[2] = wrap_angle(d[2])
    return d


def _mahalanobis2(z: ArrayLike, x: NDArray[np.float64], S: NDArray[np.float64]) -> float:
    d = _innovation(z, x)
    return float(d @ np.linalg.solve(S, d))
