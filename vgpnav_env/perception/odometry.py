"""Visual odometry: the robot's motion between consecutive camera frames from their two-view geometry.

:class:`VisualOdometry` matches each frame's RootSIFT features (shared in the process with
retrieval and the classical backbone, :func:`~vgpnav_env.perception.backbones.classical.rootsift`)
against the previous frame's and estimates their relative pose with the classical backbone's
5-point LO-RANSAC (:meth:`~vgpnav_env.perception.backbones.classical.ClassicalBackbone.relative_pose`).
A two-view pose is known up to scale: it measures the robot's yaw change and the heading of its
displacement (in the previous robot frame), not its length. :func:`fuse_motion` combines that with
wheel odometry (forward m, left m, yaw rad; its covariance) into one motion and covariance for
:meth:`~vgpnav_env.perception.state.EKFState.predict_odometry`: the metric length comes from the
odometry, a visual measurement far from the odometry (chi-square gate) is dropped.

Frames: the camera is ``camera_T_wc`` of the robot (:func:`vgpnav_env.robot.camera_T_wc`) at the
calibrated height and pitch; yaw counter-clockwise, radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vgpnav_env.geometry import PinholeCamera, wrap_angle
from vgpnav_env.perception.backbones.classical import ClassicalBackbone, Features, rootsift
from vgpnav_env.perception.resolution import downscale
from vgpnav_env.robot import camera_T_wc


@dataclass(frozen=True)
class VOConfig:
    """Visual odometry's measurement noise and gates: ``yaw_sigma_deg`` of the yaw change,
    ``heading_sigma_deg`` of the displacement's heading (used when the odometry moved at least
    ``min_step`` m), ``gate_chi2`` (2 degrees of freedom) against the odometry."""

    yaw_sigma_deg: float = 0.5
    heading_sigma_deg: float = 2.0
    min_step: float = 0.05
    gate_chi2: float = 9.2

    def __post_init__(self) -> None:
        if min(self.yaw_sigma_deg, self.heading_sigma_deg, self.min_step, self.gate_chi2) <= 0:
            raise ValueError(f"visual odometry sigmas and gates must be positive, got {self}")


@dataclass(frozen=True)
class VisualMotion:
    """One frame-to-frame measurement: ``yaw`` change and the ``heading`` of the displacement
    (radians, in the previous robot frame), from ``n_inliers`` verified matches."""

    yaw: float
    heading: float
    n_inliers: int


class VisualOdometry:
    """Frame-to-frame relative motion of a robot whose camera sits at ``height`` m, pitched
    ``pitch`` rad down (see the module docstring), from images of ``camera``'s size or larger
    (downscaled to it: :mod:`~vgpnav_env.perception.resolution`); ``backbone`` supplies the features
    and the two-view solver (default: a :class:`ClassicalBackbone`)."""

    def __init__(
        self, camera: PinholeCamera, height: float, pitch: float, backbone: ClassicalBackbone | None = None
    ) -> None:
        self.camera = camera
        self.backbone = backbone or ClassicalBackbone()
        self._mount = camera_T_wc((0.0, 0.0, 0.0), height, pitch)[:3, :3]  # robot -> camera axes
        self._previous: Features | None = None

    def reset(self, rgb: NDArray[np.uint8]) -> None:
        """A new sequence starting at ``rgb``."""
        self._previous = rootsift(downscale(rgb, self.camera), self.backbone.config)

    def measure(self, rgb: NDArray[np.uint8]) -> VisualMotion | None:
        """The motion from the previous frame to ``rgb`` (None: the two views did not match)."""
        features = rootsift(downscale(rgb, self.camera), self.backbone.config)
        previous, self._previous = self._previous, features
        if previous is None:
            return None
        pair, n_inliers, _ = self.backbone.relative_pose(features, previous, self.camera)
        if pair is None:
            return None
        # x_prev = R x_cur + t (camera axes): the current camera's rotation and centre in the
        # previous camera, turned into the previous robot frame by the mount rotation.
        R = self._mount @ pair.R @ self._mount.T
        d = self._mount @ pair.t
        return VisualMotion(float(np.arctan2(R[1, 0], R[0, 0])), float(np.arctan2(d[1], d[0])), n_inliers)


def fuse_motion(
    odometry: ArrayLike,
    covariance: ArrayLike,
    visual: VisualMotion | None,
    config: VOConfig | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64], bool]:
    """Wheel ``odometry`` (forward m, left m, yaw rad) with its 3x3 ``covariance``, corrected by a
    ``visual`` measurement (an EKF update on the motion): (motion, covariance, whether the visual
    measurement was used). The displacement's heading counts only when the odometry moved at least
    ``config.min_step``; a measurement outside the chi-square gate is dropped."""
    cfg = config or VOConfig()
    m, P = np.asarray(odometry, float), np.asarray(covariance, float)
    if visual is None:
        return m, P, False
    step = float(np.hypot(m[0], m[1]))
    rows = [np.array([0.0, 0.0, 1.0])]
    residual = [wrap_angle(visual.yaw - m[2])]
    sigmas = [np.radians(cfg.yaw_sigma_deg)]
    if step >= cfg.min_step:
        rows.append(np.array([-m[1], m[0], 0.0]) / step**2)  # d atan2(left, forward)
        residual.append(wrap_angle(visual.heading - np.arctan2(m[1], m[0])))
        sigmas.append(np.radians(cfg.heading_sigma_deg))
    H, r, R = np.array(rows), np.array(residual), np.diag(np.square(sigmas))
    S = H @ P @ H.T + R
    if float(r @ np.linalg.solve(S, r)) > cfg.gate_chi2:
        return m, P, False
    K = P @ H.T @ np.linalg.inv(S)
    I_K = np.eye(3) - K @ H
    return m + K @ r, I_K @ P @ I_K.T + K @ R @ K.T, True
