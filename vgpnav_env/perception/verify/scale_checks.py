"""Checks of the metric pose and scale before verification: the camera's height above the
anchored ground, the ground scale against the rays' scale, a plausible median depth."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from vgpnav_env.perception.motion_averaging import MotionResult
from vgpnav_env.perception.scale_recovery import GroundAnchor, GroundEstimate, ScaleEstimate
from vgpnav_env.perception.verify.config import VerifyConfig


def check_height(
    motion: MotionResult, anchor: GroundAnchor, camera_height: float, config: VerifyConfig
) -> MotionResult:
    """``motion``, or a failed copy ("camera height off by ...") when its averaged pose puts the
    camera more than ``pose_height_tolerance`` from ``camera_height`` above the anchored ground
    (only once the anchor is set; single-reference poses have no metric height yet)."""
    tol = config.pose_height_tolerance
    if tol is None or not motion.ok or motion.reason == "single reference" or not anchor.initialized:
        return motion
    off = anchor.camera_height(motion.T_wq) - camera_height
    if abs(off) <= tol:
        return motion
    return replace(motion, ok=False, reason=f"camera height off by {off:+.2f} m")


def check_scale(
    estimate: ScaleEstimate,
    ray_scale: float,
    config: VerifyConfig,
    ray_weight: float = float("inf"),
    ground: GroundEstimate | None = None,
) -> ScaleEstimate:
    """A ground scale more than ``scale_check_ratio`` away from the ray-implied ``ray_scale``
    (metres per backbone unit) is replaced by ``ray_scale`` (source "fallback"), unless the rays
    are weak (total weight ``ray_weight`` < ``strong_rays_weight``) and the ``ground`` peak has at
    most ``max_under_ground`` of the points under it (see :class:`VerifyConfig`)."""
    r = config.scale_check_ratio
    if r is None or estimate.source != "ground" or not (np.isfinite(ray_scale) and ray_scale > 0):
        return estimate
    if 1.0 / r <= estimate.scale / ray_scale <= r:
        return estimate
    weak = config.strong_rays_weight is not None and ray_weight < config.strong_rays_weight
    if weak and ground is not None and ground.found and ground.below <= config.max_under_ground:
        return estimate
    return ScaleEstimate(float(ray_scale), "fallback")


def plausible_scale(estimate: ScaleEstimate, median_depth_b: float, config: VerifyConfig) -> ScaleEstimate:
    """``estimate``, or no scale (source "none") when it puts the median confident query depth
    ``median_depth_b`` (backbone units) nearer than ``config.min_median_depth_m``."""
    floor = config.min_median_depth_m
    if floor is None or not estimate.ok or not np.isfinite(median_depth_b):
        return estimate
    if estimate.scale * median_depth_b >= floor:
        return estimate
    return ScaleEstimate(float("nan"), "none")
