"""Settings of verification (:class:`VerifyConfig`) and the caller's pose gate (:class:`PoseGate`).
The recovery strategies' settings are :class:`~vgpnav_env.perception.recovery.RecoveryConfig`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from vgpnav_env.geometry import camera_yaw_pitch, wrap_angle


@dataclass(frozen=True)
class VerifyConfig:
    """Settings of the scale checks and of the verdict on a pose; None switches one off.

    Match counts are per reference pair; angles in degrees; distances in metres.

    Attributes:
        pose_height_tolerance: the camera's height above the anchored ground may differ from the
            calibrated camera height by at most this (else the pose fails like a failed consensus).
        scale_check_ratio: when the ground scale and the rays' implied scale differ by more than
            this factor (> 1), the ground peak is something else (a table top) and the rays'
            scale is used, if the rays are strong or the peak has points under it (below).
        strong_rays_weight: the rays overrule the ground only with at least this total
            motion-averaging weight ...
        max_under_ground: ... or when more than this fraction of the points lie under the ground
            peak (a table top leaves the floor below it).
        min_median_depth_m: a scale that puts the median confident query depth nearer than this
            is no scale.
        max_epipolar_error_px: a match supports a pose when its epipolar error is at most this.
        min_support_matches: a reference supports a pose when it explains at least this many
            matches.
        min_supporting_references: a pose (or a rival) needs this many supporting references ...
        single_reference_support: ... or one reference explaining at least this many matches.
        min_total_support: the supporting references must explain this many matches together
            (the "support" check).
        rival_distance: a rival pose is distinct when farther than this ...
        rival_angle_deg: ... or turned by more than this.
        ambiguity_ratio: a distinct rival whose support reaches this share of the pose's makes
            the frame "ambiguous".
        plane_threshold_px: matches no homography of the pair explains within this are off its
            dominant plane (None: no plane check).
        min_off_plane_matches: a pose (and a rival, to count) must explain this many off-plane
            matches of one reference: matches on one wall fit any room with that wallpaper.
        min_explained_confidence: the pose must explain at least this share of the backbone's
            confidence in the pairs (:func:`explained_confidence`).
        rival_claim_ratio: a reference the pose explains in less than this share of what a rival
            explains counts for the rival too (None: only references the pose does not explain).
        ambiguity_references: the pose and a rival are compared by the support of their this many
            strongest references (None: all).
        max_roll_deg: the camera's roll must stay within this (the "mount" check) ...
        pitch_range_deg: ... and its downward pitch within this range.
        prior_max_roll_deg: a pose inside a state estimate's prior counts as placed by it only
            with its roll within this.
        confidence_matches: the support that halves a pose's score:
            ``strength / (strength + rival_strength + confidence_matches)``.
        rival_confidence_ratio: a distinct rival whose most confident pair reaches this share of
            the confidence of the pose's best supporting pair makes the frame "ambiguous" (None:
            off) ...
        confident_rival_off_plane: ... when that rival explains this many off-plane matches.
        decision: "rules" (the checks above decide) or "model" (the calibrated model of
            :mod:`~vgpnav_env.perception.verify.model` decides from the pose's size-free evidence;
            the mount checks stay).
        accept_probability: with the model, a pose is accepted when its probability of being right
            (within 5 cm / 5 deg) is at least this: a confidently wrong pose costs the map and the
            episode, a lost frame a little.

    Where the defaults came from: ``benchmarks/history/tuning.md``.
    """

    pose_height_tolerance: float | None = 0.3
    scale_check_ratio: float | None = 1.5
    strong_rays_weight: float | None = 0.2
    max_under_ground: float = 0.03
    min_median_depth_m: float | None = 0.25
    max_epipolar_error_px: float = 2.0
    min_support_matches: int = 30
    min_supporting_references: int = 2
    single_reference_support: int | None = 100
    min_total_support: int | None = 140
    rival_distance: float = 0.5
    rival_angle_deg: float = 10.0
    ambiguity_ratio: float = 0.5
    plane_threshold_px: float | None = 2.0
    min_off_plane_matches: int = 20
    min_explained_confidence: float | None = 0.45
    rival_claim_ratio: float | None = 0.5
    ambiguity_references: int | None = 2
    max_roll_deg: float | None = 5.0
    prior_max_roll_deg: float = 1.5
    pitch_range_deg: tuple[float, float] | None = (5.0, 40.0)
    confidence_matches: float = 100.0
    rival_confidence_ratio: float | None = 0.9
    confident_rival_off_plane: int = 10
    decision: str = "rules"
    accept_probability: float = 0.9

    def __post_init__(self) -> None:
        if self.decision not in ("rules", "model") or not 0 < self.accept_probability < 1:
            raise ValueError(
                f"need decision 'rules' or 'model' and 0 < accept_probability < 1, got "
                f"{self.decision!r}, {self.accept_probability}"
            )
        if self.scale_check_ratio is not None and self.scale_check_ratio <= 1:
            raise ValueError(f"scale_check_ratio must be > 1 or None, got {self.scale_check_ratio}")
        if self.strong_rays_weight is not None and self.strong_rays_weight <= 0:
            raise ValueError(f"strong_rays_weight must be > 0 or None, got {self.strong_rays_weight}")
        if not 0 <= self.max_under_ground <= 1:
            raise ValueError(f"max_under_ground must be in [0, 1], got {self.max_under_ground}")
        if self.min_median_depth_m is not None and self.min_median_depth_m <= 0:
            raise ValueError(f"min_median_depth_m must be > 0 m or None, got {self.min_median_depth_m}")
        if self.pose_height_tolerance is not None and self.pose_height_tolerance <= 0:
            raise ValueError(f"pose_height_tolerance must be > 0 m or None, got {self.pose_height_tolerance}")
        if (
            self.max_epipolar_error_px <= 0
            or self.min_support_matches < 1
            or self.min_supporting_references < 1
        ):
            raise ValueError(
                "need max_epipolar_error_px > 0, min_support_matches >= 1 and min_supporting_references >= 1"
            )
        if self.plane_threshold_px is not None and self.plane_threshold_px <= 0:
            raise ValueError(f"plane_threshold_px must be > 0 px or None, got {self.plane_threshold_px}")
        if self.single_reference_support is not None and self.single_reference_support < 1:
            raise ValueError(
                f"single_reference_support must be >= 1 or None, got {self.single_reference_support}"
            )
        if self.min_total_support is not None and self.min_total_support < 1:
            raise ValueError(f"min_total_support must be >= 1 or None, got {self.min_total_support}")
        if self.min_off_plane_matches < 1:
            raise ValueError(f"min_off_plane_matches must be >= 1, got {self.min_off_plane_matches}")
        if self.min_explained_confidence is not None and not 0 < self.min_explained_confidence <= 1:
            raise ValueError(
                f"min_explained_confidence must be in (0, 1] or None, got {self.min_explained_confidence}"
            )
        if not self.prior_max_roll_deg > 0:
            raise ValueError(f"prior_max_roll_deg must be > 0 deg, got {self.prior_max_roll_deg}")
        if self.ambiguity_references is not None and self.ambiguity_references < 1:
            raise ValueError(f"ambiguity_references must be >= 1 or None, got {self.ambiguity_references}")
        if self.rival_claim_ratio is not None and not 0 < self.rival_claim_ratio <= 1:
            raise ValueError(f"rival_claim_ratio must be in (0, 1] or None, got {self.rival_claim_ratio}")
        if self.rival_confidence_ratio is not None and not self.rival_confidence_ratio > 0:
            raise ValueError(f"rival_confidence_ratio must be > 0 or None, got {self.rival_confidence_ratio}")
        if self.confident_rival_off_plane < 0:
            raise ValueError(f"confident_rival_off_plane must be >= 0, got {self.confident_rival_off_plane}")
        if not 0 < self.ambiguity_ratio <= 1 or self.confidence_matches <= 0:
            raise ValueError(
                f"need 0 < ambiguity_ratio <= 1 and confidence_matches > 0, got "
                f"{self.ambiguity_ratio}, {self.confidence_matches}"
            )


@dataclass(frozen=True)
class PoseGate:
    """Where the caller expects the robot (e.g. its last fix moved by odometry): the planar ``pose``
    (x, y, yaw) in W. A camera pose whose horizontal position is more than ``max_distance`` metres
    from (x, y), or whose heading (camera yaw) differs from yaw by more than ``max_yaw`` radians, is
    lost ("inconsistent motion") and is not fused into the map. One wrong reference set can place a
    frame metres away; a robot cannot jump there in one step.
    """

    pose: NDArray[np.float64]
    max_distance: float
    max_yaw: float

    def __post_init__(self) -> None:
        if np.shape(self.pose) != (3,):
            raise ValueError(f"PoseGate.pose must be a planar (x, y, yaw), got shape {np.shape(self.pose)}")
        if not (self.max_distance > 0 and self.max_yaw > 0):
            raise ValueError(
                f"max_distance (m) and max_yaw (rad) must be positive, "
                f"got {self.max_distance}, {self.max_yaw}"
            )

    def deviation(self, T_wc: NDArray[np.float64]) -> tuple[float, float]:
        """(horizontal distance m, absolute heading difference rad) of the camera ``T_wc`` from the
        gate's pose."""
        distance = float(np.linalg.norm(T_wc[:2, 3] - np.asarray(self.pose[:2], float)))
        yaw = abs(float(wrap_angle(camera_yaw_pitch(T_wc)[0] - self.pose[2])))
        return distance, yaw

    def admits(self, T_wc: NDArray[np.float64]) -> bool:
        distance, yaw = self.deviation(T_wc)
        return distance <= self.max_distance and yaw <= self.max_yaw
