"""Is this pose true? The checks a frame's pose must pass before VGP-Nav uses it, and its second chances.

The :class:`~vgpnav_env.perception.pipeline.Perceiver` runs the paper's stages; everything that
makes localization robust beyond them lives here, with its settings in :class:`VerifyConfig`
(``PerceptionConfig.verify``):

- checks (a pose that fails one is not used):
  :func:`check_height` -- a ground robot's camera stays at its calibrated height above the
  anchored ground; :func:`check_scale` -- the ground scale must agree with the scale the
  motion-averaging rays imply, else the ground peak was something else; :class:`PoseGate` -- the
  caller's expectation (e.g. odometry since the last fix);
- second chances when the first answer is weak:
  :func:`second_round_references` -- references chosen around the first round's pose
  hypotheses, the better round kept (:func:`round_rank`); :func:`single_pair_fallback` -- the
  pose of the most confident pair alone when motion averaging fails.

Poses are ``T_wc`` / ``T_wq`` (OpenCV camera -> world, metres); backbone translations are in the
backbone's unknown units until a scale (metres per unit) is applied.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from vgpnav_env.geometry import (
    PinholeCamera,
    camera_yaw_pitch,
    invert_pose,
    make_pose,
    rotation_angle,
    wrap_angle,
)
from vgpnav_env.perception.backbones.base import BackboneOutput
from vgpnav_env.perception.backbones.classical import (
    dominant_plane,
    sampson_distance,
    triangulate_query_depth,
)
from vgpnav_env.perception.motion_averaging import (
    MotionAveragingConfig,
    MotionResult,
    average_motion,
    pair_centre,
)
from vgpnav_env.perception.retrieval import pose_guided_references
from vgpnav_env.perception.scale_recovery import GroundAnchor, GroundEstimate, ScaleEstimate


@dataclass(frozen=True)
class VerifyConfig:
    """Settings of the checks and second chances (module docstring); None switches one off.

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
        second_round_below_inliers: with fewer consistent references than this (a failed pose
            counts 0) a second round verifies references chosen around the first round's pose
            hypotheses; the round with more consistent references wins (None: one round).
        second_round_hypotheses: at most this many distinct pose hypotheses seed the second round.
        second_round_radius: its database cameras lie within this distance of a hypothesis ...
        second_round_max_angle_deg: ... and within this angle of its heading.
        single_fallback_confidence: when motion averaging fails, a pair at least this confident
            gives the pose alone, placed with the ground scale (needs scale recovery).
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
        prior_hypotheses: a frame lost inside a prior gets up to this many pose hypotheses there
            (:func:`prior_poses`) ...
        prior_grid_m: ... whose positions are searched on a grid of this step.
        prior_support_per_m: a pose placed inside the prior needs this many supporting matches per
            metre of the prior's radius, at most ``min_total_support`` (:func:`prior_support_floor`;
            None: ``min_total_support``).
        confidence_matches: the support that halves a pose's score:
            ``strength / (strength + rival_strength + confidence_matches)``.
        ray_slide_share: a verified pose whose position one pair's ray carries (at least this
            share of the translation weight) may slide along that ray (:func:`slide_on_ray`;
            None: never) ...
        ray_slide_gain: ... to where the other references explain this fraction more matches ...
        ray_slide_max_shift: ... by at most this distance.
        rival_confidence_ratio: a distinct rival whose most confident pair reaches this share of
            the confidence of the pose's best supporting pair makes the frame "ambiguous" (None:
            off) ...
        confident_rival_off_plane: ... when that rival explains this many off-plane matches.

    Where the defaults came from: ``benchmarks/history/tuning.md``.
    """

    pose_height_tolerance: float | None = 0.3
    scale_check_ratio: float | None = 1.5
    strong_rays_weight: float | None = 0.2
    max_under_ground: float = 0.03
    min_median_depth_m: float | None = 0.25
    second_round_below_inliers: int | None = 3
    second_round_hypotheses: int = 2
    second_round_radius: float = 1.5
    second_round_max_angle_deg: float = 35.0
    single_fallback_confidence: float | None = 0.15
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
    prior_hypotheses: int = 3
    prior_grid_m: float = 0.08
    prior_support_per_m: float | None = 350.0
    pitch_range_deg: tuple[float, float] | None = (5.0, 40.0)
    confidence_matches: float = 100.0
    ray_slide_share: float | None = 0.55
    ray_slide_gain: float = 0.1
    ray_slide_max_shift: float = 0.3
    rival_confidence_ratio: float | None = 0.9
    confident_rival_off_plane: int = 10

    def __post_init__(self) -> None:
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
        if self.second_round_hypotheses < 1 or self.second_round_radius <= 0:
            raise ValueError("need second_round_hypotheses >= 1 and second_round_radius > 0 m")
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
        if self.prior_support_per_m is not None and not self.prior_support_per_m > 0:
            raise ValueError(f"prior_support_per_m must be > 0 or None, got {self.prior_support_per_m}")
        if not self.prior_max_roll_deg > 0:
            raise ValueError(f"prior_max_roll_deg must be > 0 deg, got {self.prior_max_roll_deg}")
        if self.ambiguity_references is not None and self.ambiguity_references < 1:
            raise ValueError(f"ambiguity_references must be >= 1 or None, got {self.ambiguity_references}")
        if self.rival_claim_ratio is not None and not 0 < self.rival_claim_ratio <= 1:
            raise ValueError(f"rival_claim_ratio must be in (0, 1] or None, got {self.rival_claim_ratio}")
        if self.ray_slide_share is not None and not 0 < self.ray_slide_share <= 1:
            raise ValueError(f"ray_slide_share must be in (0, 1] or None, got {self.ray_slide_share}")
        if self.ray_slide_gain < 0 or not self.ray_slide_max_shift > 0:
            raise ValueError(
                f"need ray_slide_gain >= 0 and ray_slide_max_shift > 0 m, got "
                f"{self.ray_slide_gain}, {self.ray_slide_max_shift}"
            )
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


def epipolar_support(
    T_wq: NDArray[np.float64],
    T_wi: NDArray[np.float64],
    matches: Sequence[NDArray[np.floating]],
    camera: PinholeCamera,
    max_error_px: float,
) -> NDArray[np.int64]:
    """How many of each reference's feature matches the pose ``T_wq`` explains: (k,) counts.

    ``T_wi`` (k, 4, 4): the references' poses; ``matches``: per reference (m_i, 4) pixels
    ``(u_q, v_q, u_i, v_i)`` (:attr:`BackboneOutput.matches`). Under the relative pose
    ``T_iq = T_wi^-1 T_wq`` a match counts when its Sampson distance to the epipolar geometry is
    below ``max_error_px`` (pixels, at the camera's focal length) and its triangulated point lies
    in front of both cameras; a reference at the query's centre (under 1 mm) is a pure rotation
    and its matches are checked by reprojection. This
    uses nothing of how the pose was found (retrieval, motion averaging), so it checks any pose
    hypothesis against any references the query was matched with.
    """
    T_wi = np.asarray(T_wi, float).reshape(-1, 4, 4)
    if len(matches) != len(T_wi):
        raise ValueError(f"got {len(matches)} match arrays for {len(T_wi)} reference poses")
    K_inv = np.linalg.inv(camera.K)
    f = float(np.sqrt(camera.K[0, 0] * camera.K[1, 1]))
    out = np.zeros(len(T_wi), np.int64)
    for i, (T, m) in enumerate(zip(T_wi, matches, strict=True)):
        m = np.asarray(m, float).reshape(-1, 4)
        if len(m) == 0:
            continue
        T_iq = invert_pose(T) @ T_wq
        R, t = T_iq[:3, :3], T_iq[:3, 3]
        x_q = np.c_[m[:, :2], np.ones(len(m))] @ K_inv.T
        x_i = np.c_[m[:, 2:], np.ones(len(m))] @ K_inv.T
        Rx = x_q @ R.T
        if np.linalg.norm(t) < 1e-3:
            with np.errstate(divide="ignore", invalid="ignore"):
                err = f * np.linalg.norm(Rx[:, :2] / Rx[:, 2:3] - x_i[:, :2], axis=1)
        else:
            err = f * sampson_distance(x_q, x_i, R, t)
            err[~triangulate_query_depth(x_q, x_i, R, t)[2]] = np.inf
        out[i] = int(np.count_nonzero(np.nan_to_num(err, nan=np.inf) < max_error_px))
    return out


def off_plane_matches(out: BackboneOutput, threshold_px: float) -> BackboneOutput:
    """``out`` with each reference's ``matches`` reduced to those off the pair's dominant plane: the
    matches that the homography RANSAC (OpenCV, ``threshold_px`` pixels) fits to most of them does
    not explain. A pair under 8 matches keeps none. Without matches, ``out`` unchanged."""
    if out.matches is None:
        return out
    kept = []
    for m in out.matches:
        m = np.asarray(m, np.float32).reshape(-1, 4)
        if len(m) < 8:
            kept.append(m[:0])
            continue
        kept.append(m[~dominant_plane(m[:, :2], m[:, 2:], threshold_px)])
    return replace(out, matches=kept)


def reference_support(
    T_wq: NDArray[np.float64],
    T_wi: NDArray[np.float64],
    out: BackboneOutput,
    camera: PinholeCamera,
    config: VerifyConfig,
) -> NDArray[np.int64]:
    """(k,) matches of each reference that the pose ``T_wq`` explains: :func:`epipolar_support` of
    the backbone's ``matches``; a backbone without matches (``matches`` None) counts a pair's
    ``n_matches`` when its own relative pose agrees with ``T_wq`` (rotation and direction of the
    query centre seen from the reference within ``rival_angle_deg``), else 0."""
    if out.matches is not None:
        return epipolar_support(T_wq, T_wi, out.matches, camera, config.max_epipolar_error_px)
    T_iq_pose = invert_pose(T_wi) @ T_wq
    T_iq = out.T_iq
    limit = np.deg2rad(config.rival_angle_deg)
    agree = np.zeros(len(T_wi), bool)
    for i in range(len(T_wi)):
        if out.confidence[i] <= 0:
            continue
        a, b = T_iq_pose[i, :3, 3], T_iq[i, :3, 3]
        cos = float(a @ b) / max(float(np.linalg.norm(a) * np.linalg.norm(b)), 1e-12)
        same_direction = np.arccos(np.clip(cos, -1.0, 1.0)) <= limit
        agree[i] = rotation_angle(T_iq_pose[i, :3, :3], T_iq[i, :3, :3]) <= limit and same_direction
    return np.where(agree, out.n_matches, 0).astype(np.int64)


def pair_support(
    T_wi: NDArray[np.float64], out: BackboneOutput, camera: PinholeCamera, config: VerifyConfig
) -> NDArray[np.int64]:
    """(k,) matches of each pair that the pair's own relative pose ``T_iq`` explains (the query
    where that pair alone puts it, :func:`epipolar_support`); a backbone without matches: its
    ``n_matches``. Pairs without confidence count 0."""
    if out.matches is None:
        return np.where(out.confidence > 0, out.n_matches, 0).astype(np.int64)
    own = np.zeros(len(T_wi), np.int64)
    for i in np.flatnonzero(out.confidence > 0):
        T = T_wi[i] @ out.T_iq[i]
        own[i] = epipolar_support(T, T_wi[i][None], [out.matches[i]], camera, config.max_epipolar_error_px)[0]
    return own


def explained_confidence(
    T_wq: NDArray[np.float64],
    T_wi: NDArray[np.float64],
    out: BackboneOutput,
    camera: PinholeCamera,
    config: VerifyConfig,
    support: NDArray[np.int64] | None = None,
    own: NDArray[np.int64] | None = None,
) -> float:
    """The share in [0, 1] of the backbone's pair confidence that the pose ``T_wq`` explains:
    ``sum_i c_i min(1, s_i / o_i) / sum_i c_i`` over the pairs with confidence ``c_i > 0``, where
    ``s_i`` counts the matches of pair i the pose explains (:func:`reference_support`; ``support``
    when already computed) and ``o_i`` those the pair's own relative pose ``T_iq`` explains
    (:func:`pair_support`; ``own`` when already computed). 0 when no pair has confidence.
    """
    c = np.asarray(out.confidence, float)
    pairs = np.flatnonzero(c > 0)
    if len(pairs) == 0:
        return 0.0
    s = reference_support(T_wq, T_wi, out, camera, config) if support is None else np.asarray(support)
    own = (pair_support(T_wi, out, camera, config) if own is None else np.asarray(own))[pairs]
    share = np.minimum(s[pairs] / np.maximum(own, 1.0), 1.0)
    return float((c[pairs] * share).sum() / c[pairs].sum())


#: The checks of :func:`verify_pose`, in the order they run: name -> what rejects a pose
#: (:attr:`Verdict.check`; "ambiguity" gives the lost reason "ambiguous", the others "unverified").
VERIFY_CHECKS: dict[str, str] = {
    "mount": "the camera's roll, pitch or height is not the robot mount's",
    "support": "too few references, or too few matches, explain the pose (epipolar support)",
    "plane": "the pose explains matches only on the pairs' dominant planes",
    "ambiguity": "a distinct rival pose has comparable support",
    "share": "the pose explains too small a share of the pairs' confidence",
}


@dataclass(frozen=True)
class Evidence:
    """What the images say about one pose, in quantities that do not depend on the image size or
    the feature budget (shares and ratios of match counts), for the calibrated model.

    ``match_share``: the matches of the confident pairs the pose explains, over all their matches;
    ``explained_share``: the pair confidence it explains (:func:`explained_confidence`);
    ``agree_share``: the confident pairs whose own pose's matches it explains at least half of;
    ``rival_margin`` in [-1, 1]: ``(s - r) / (s + r)`` of the pose's support ``s`` and the
    strongest distinct rival's ``r`` (1 without a rival); ``off_plane_share``: the matches off its
    dominant plane of the pose's best reference, over that reference's explained matches;
    ``confident_rival``: a distinct rival has a pair as confident as the pose's best (0 / 1);
    ``roll_deg`` / ``height_off_m``: the mount; ``placed``: inside a state estimate's prior (0 / 1).
    The counts behind them (``strength``, ``rival_strength``, ``off_plane``, ``n_matches``,
    ``n_supporting``, ``n_pairs``) are kept for analysis, not for the model.
    """

    match_share: float
    explained_share: float
    agree_share: float
    rival_margin: float
    off_plane_share: float
    confident_rival: float
    roll_deg: float
    height_off_m: float
    placed: float
    strength: int
    rival_strength: int
    off_plane: int
    n_matches: int
    n_supporting: int
    n_pairs: int

    @classmethod
    def of(
        cls,
        raw: NDArray[np.int64],
        own: NDArray[np.int64],
        out: BackboneOutput,
        *,
        off_plane: int,
        rival_strength: int,
        rival_confidence: bool,
        roll_deg: float,
        height_off_m: float,
        placed: bool,
        ambiguity_references: int | None,
        min_support: int,
    ) -> Evidence:
        """The evidence of a pose from its per-reference support ``raw`` (k,), the pairs' own
        support ``own`` (k,), the backbone output and the rival / plane / mount numbers."""
        c = np.asarray(out.confidence, float)
        pairs = c > 0
        if out.matches is not None:
            n = np.array([len(np.asarray(m).reshape(-1, 4)) for m in out.matches], float)
        else:
            n = np.asarray(out.n_matches, float)
        raw, own = np.asarray(raw, float), np.asarray(own, float)
        total = float(n[pairs].sum())
        share = np.minimum(raw / np.maximum(own, 1.0), 1.0)
        supporting = raw >= min_support
        s = float(np.sort(np.where(supporting, raw, 0.0))[::-1][:ambiguity_references].sum())
        best = float(raw[supporting].max(initial=0.0))
        return cls(
            match_share=float(raw[pairs].sum() / total) if total > 0 else 0.0,
            explained_share=float((c[pairs] * share[pairs]).sum() / c[pairs].sum()) if pairs.any() else 0.0,
            agree_share=float(((raw >= 0.5 * own) & (own > 0))[pairs].mean()) if pairs.any() else 0.0,
            rival_margin=(s - rival_strength) / (s + rival_strength) if s + rival_strength > 0 else 0.0,
            off_plane_share=min(1.0, off_plane / best) if best > 0 else 0.0,
            confident_rival=float(rival_confidence),
            roll_deg=float(roll_deg),
            height_off_m=float(height_off_m) if np.isfinite(height_off_m) else 0.0,
            placed=float(placed),
            strength=int(raw[supporting].sum()),
            rival_strength=int(rival_strength),
            off_plane=int(off_plane),
            n_matches=int(total),
            n_supporting=int(supporting.sum()),
            n_pairs=int(pairs.sum()),
        )


@dataclass(frozen=True)
class Verdict:
    """Whether the images confirm a pose (:func:`verify_pose`).

    ``ok``; ``reason``: "" or a lost reason ("unverified": too little support, a tilted camera or
    a wrong camera height; "ambiguous": a distinct rival pose has comparable support);
    ``detail``: the numbers behind it. ``support`` (k,): matches per reference the pose explains;
    ``strength``: their sum over the supporting references (at least ``min_support_matches``);
    ``rival_strength``: the strongest distinct rival's support from references the pose does
    not explain, or in small part (over its ``ambiguity_references`` strongest; 0 without one)
    and ``rival`` its pose. ``score`` in [0, 1):
    ``strength / (strength + rival_strength + confidence_matches)`` -- more independent support,
    higher; a rival, lower; ``confidence``: the score of an accepted pose, else 0. ``check``: the
    :data:`VERIFY_CHECKS` name of the check that rejected the pose ("" when ok). ``by_prior``: ok
    only inside a state estimate's prior (:func:`verify_pose`'s ``prior``): the images alone, with
    every rival and check, would not confirm the pose. With a prior, ``rival_strength`` / ``rival``
    are those of the rivals inside it.
    """

    ok: bool
    reason: str
    detail: str
    score: float
    support: NDArray[np.int64]
    strength: int
    rival_strength: int = 0
    rival: NDArray[np.float64] | None = None
    check: str = ""
    by_prior: bool = False
    evidence: Evidence | None = None

    @property
    def n_supporting(self) -> int:
        return int(np.count_nonzero(self.support))

    @property
    def confidence(self) -> float:
        return self.score if self.ok else 0.0


def verify_pose(
    T_wq: NDArray[np.float64],
    T_wi: NDArray[np.float64],
    out: BackboneOutput,
    camera: PinholeCamera,
    config: VerifyConfig,
    *,
    rivals: Sequence[NDArray[np.float64]] = (),
    camera_z: float = float("nan"),
    own: NDArray[np.int64] | None = None,
    prior: PoseGate | None = None,
) -> Verdict:
    """Check the pose ``T_wq`` (metric, W) against the query's matches with references ``T_wi``
    (k, 4, 4; ``out``: the backbone output of the query with exactly these references).

    The pose must keep the camera's roll and pitch of a ground robot's mount (``max_roll_deg``,
    ``pitch_range_deg``) and its height (within ``pose_height_tolerance`` of ``camera_z``, the
    world z of the calibrated camera above the anchored ground; nan = unknown), and explain at
    least ``min_support_matches`` matches of each of at least ``min_supporting_references``
    references (:func:`reference_support`), or one reference explaining ``single_reference_support``
    matches, together at least ``min_total_support``; else "unverified". Each pose of ``rivals`` that a
    ground robot's camera could have (the same mount checks) and lies
    farther than ``rival_distance`` metres or ``rival_angle_deg`` from ``T_wq`` is scored by the
    support it gets from the references ``T_wq`` does not explain, or explains in less than
    ``rival_claim_ratio`` of what the rival does (at least
    ``min_supporting_references`` of them, like the pose itself); when the strongest reaches
    ``ambiguity_ratio`` times the pose's own (each the support of its ``ambiguity_references``
    strongest references), two places fit the images: "ambiguous"; so they do when such a rival,
    with ``confident_rival_off_plane`` matches off one pair's dominant plane, has a pair at least
    ``rival_confidence_ratio`` times as confident as the pose's most confident supporting pair. With
    ``plane_threshold_px``, the pose must explain ``min_off_plane_matches`` matches off the
    dominant plane of one supporting reference (else "unverified"), and so must a rival of its
    own references to count. With ``min_explained_confidence``, the pose must explain that share of
    the pairs' confidence (:func:`explained_confidence`), else "unverified". Nothing here depends
    on how the pose or the references were found (retrieval, tracking).

    ``prior``: where a state estimate confidently expects the camera (e.g. the EKF's gate,
    :meth:`~vgpnav_env.perception.state.EKFState.prior`; never wider than a gross error). A pose
    inside it, its camera rolled at most ``prior_max_roll_deg``, has its place from the estimate
    and needs from the images only its precise pose: rivals outside the prior do not count (the
    same view in an identical ward the robot cannot have reached), and the ``min_total_support``,
    plane and share checks are waived (the mount check and the supporting references stay). A pose
    outside it is verified as without a prior (the
    :class:`~vgpnav_env.perception.pipeline.Perceiver` then loses it as "inconsistent motion", or
    takes the rival the prior picks, :func:`prior_hypothesis`).
    """
    raw = reference_support(T_wq, T_wi, out, camera, config)
    support = np.where(raw >= config.min_support_matches, raw, 0)
    strength = int(support.sum())
    explained = support > 0
    flat = off_plane_matches(out, config.plane_threshold_px) if config.plane_threshold_px else None

    def off_plane(T: NDArray[np.float64], among: NDArray[np.bool_]) -> int:
        """The most matches off its dominant plane that one reference of ``among`` gives ``T``."""
        if flat is None or not among.any():
            return config.min_off_plane_matches if flat is None else 0
        return int(reference_support(T, T_wi, flat, camera, config)[among].max())

    rival_strength, rival = 0, None  # the strongest distinct rival
    # A rival whose best pair is about as confident as the pose's best pair (rival_confidence_ratio).
    ratio, confident = config.rival_confidence_ratio, None
    if ratio is not None and explained.any():
        confident = ratio * float(out.confidence[explained].max())
    confident_strength, confident_rival = 0, None
    inside_strength, inside = 0, None  # the strongest inside the prior (a placed pose's rival)
    claim = config.rival_claim_ratio
    placed = prior is not None and prior.admits(T_wq) and abs(_roll_deg(T_wq)) <= config.prior_max_roll_deg
    for T in rivals:
        if implausible_mount(T, camera_z, config):
            continue
        distinct = np.linalg.norm(T[:3, 3] - T_wq[:3, 3]) > config.rival_distance or rotation_angle(
            T[:3, :3], T_wq[:3, :3]
        ) > np.deg2rad(config.rival_angle_deg)
        if not distinct:
            continue
        theirs = reference_support(T, T_wi, out, camera, config)
        claimed = ~explained if claim is None else ~explained | (raw < claim * theirs)
        theirs_alone = claimed & (theirs >= config.min_support_matches)
        if not _enough_references(theirs[theirs_alone], config):
            continue  # one weak pair alone is no place (a plane's matches fit several poses)
        structure = off_plane(T, theirs_alone)
        value = _strongest(theirs[theirs_alone], config.ambiguity_references)
        if (
            confident is not None
            and structure >= config.confident_rival_off_plane
            and float(out.confidence[theirs_alone].max()) >= confident
            and value > confident_strength
        ):
            confident_strength, confident_rival = value, T
        if structure < config.min_off_plane_matches:
            continue  # a wall's texture alone is no place either
        if value > rival_strength:
            rival_strength, rival = value, T
        if placed and prior.admits(T) and value > inside_strength:
            inside_strength, inside = value, T
    n = int(explained.sum())
    own = pair_support(T_wi, out, camera, config) if own is None else own
    evidence = Evidence.of(
        raw,
        own,
        out,
        off_plane=off_plane(T_wq, explained) if flat is not None else 0,
        rival_strength=inside_strength if placed else rival_strength,
        rival_confidence=confident_strength > 0,
        roll_deg=_roll_deg(T_wq),
        height_off_m=float(T_wq[2, 3] - camera_z),
        placed=placed,
        ambiguity_references=config.ambiguity_references,
        min_support=config.min_support_matches,
    )

    def verdict(check: str, detail: str, by_prior: bool = False) -> Verdict:
        reason = "ambiguous" if check == "ambiguity" else "unverified" if check else ""
        strongest, its = (inside_strength, inside) if placed else (rival_strength, rival)
        score = strength / (strength + strongest + config.confidence_matches)
        return Verdict(
            not reason, reason, detail, score, support, strength, strongest, its, check, by_prior, evidence
        )

    mount = implausible_mount(T_wq, camera_z, config)
    if mount:
        return verdict("mount", mount)

    def alone() -> tuple[str, str]:
        """The check the images alone fail (all rivals count, nothing waived; "" when none) and why."""
        if not _enough_references(support[explained], config):
            return "support", f"{n} reference(s) support the pose (support {raw.tolist()})"
        if config.min_total_support is not None and strength < config.min_total_support:
            return "support", f"{n} references explain only {strength} matches"
        structure = off_plane(T_wq, explained)
        if structure < config.min_off_plane_matches:
            return "plane", f"support only on the pairs' dominant planes ({structure} matches off them)"
        if rival_strength >= config.ambiguity_ratio * _strongest(support, config.ambiguity_references):
            distance = np.linalg.norm(rival[:3, 3] - T_wq[:3, 3])
            detail = f"a pose {distance:.1f} m away has support {rival_strength} against {strength}"
            return "ambiguity", detail
        if confident_rival is not None:
            distance = np.linalg.norm(confident_rival[:3, 3] - T_wq[:3, 3])
            detail = f"a pose {distance:.1f} m away has a pair as confident as the pose's best"
            return "ambiguity", detail
        if config.min_explained_confidence is not None:
            share = explained_confidence(T_wq, T_wi, out, camera, config, raw, own)
            if share < config.min_explained_confidence:
                return "share", f"the pose explains {share:.0%} of the pairs' confidence"
        return "", f"{n} references, support {strength}, rival {rival_strength}"

    if not placed:
        return verdict(*alone())
    inside_prior = _placed_verdict(verdict, support, inside, inside_strength, T_wq, config)
    return replace(inside_prior, by_prior=bool(alone()[0])) if inside_prior.ok else inside_prior


def prior_hypothesis(
    T_wq: NDArray[np.float64],
    rivals: Sequence[NDArray[np.float64]],
    T_wi: NDArray[np.float64],
    out: BackboneOutput,
    camera: PinholeCamera,
    config: VerifyConfig,
    prior: PoseGate,
    *,
    scale: float,
    averaging: MotionAveragingConfig,
    camera_z: float = float("nan"),
    own: NDArray[np.int64] | None = None,
) -> tuple[NDArray[np.float64], Verdict] | None:
    """The pose the ``prior`` picks when the images do not confirm ``T_wq`` inside it: of the
    ``rivals`` of ``T_wq`` (:func:`rival_poses`) inside the prior, the one with the most support
    that :func:`verify_pose` confirms as the pose (with the prior, against its own rivals and
    ``T_wq``), and its verdict; None when none is confirmed. In identical wards the averaged pose
    is often the other ward's view and the true place's pairs make a rival: inside the prior, it
    is the robot's. ``scale``: metres per backbone unit of the rivals' own rivals."""
    best = None
    for T in rivals:
        if not prior.admits(T):
            continue
        support = rival_pairs(reference_support(T, T_wi, out, camera, config), T_wi, out, camera, config, own)
        theirs = [T_wq, *rival_poses(T, T_wi, out, support, scale, averaging)]
        verdict = verify_pose(
            T, T_wi, out, camera, config, rivals=theirs, camera_z=camera_z, own=own, prior=prior
        )
        if verdict.ok and (best is None or verdict.strength > best[1].strength):
            best = T, verdict
    return best


def _placed_verdict(
    verdict: Callable[[str, str], Verdict],
    support: NDArray[np.int64],
    rival: NDArray[np.float64] | None,
    rival_strength: int,
    T_wq: NDArray[np.float64],
    config: VerifyConfig,
) -> Verdict:
    """The verdict of :func:`verify_pose` on a pose inside its ``prior``: enough supporting
    references (``support``, 0 under ``min_support_matches``; :func:`_enough_references`), no
    rival inside the prior as strong (``ambiguity_ratio``)."""
    if not _enough_references(support[support > 0], config):
        n = np.count_nonzero(support)
        return verdict(
            "support", f"{n} reference(s) support the pose inside the prior (support {support.tolist()})"
        )
    if rival is not None and rival_strength >= config.ambiguity_ratio * _strongest(
        support, config.ambiguity_references
    ):
        distance = np.linalg.norm(rival[:3, 3] - T_wq[:3, 3])
        detail = f"a pose {distance:.1f} m away inside the prior has support {rival_strength}"
        return verdict("ambiguity", detail)
    n, strength = np.count_nonzero(support), int(support.sum())
    return verdict("", f"inside the prior: {n} references, support {strength}")


def _roll_deg(T_wc: NDArray[np.float64]) -> float:
    """The roll (degrees) of an OpenCV camera pose ``T_wc`` about its optical axis, against gravity."""
    return float(np.degrees(np.arcsin(np.clip(T_wc[2, 0], -1.0, 1.0))))


def _strongest(support: NDArray[np.int64], m: int | None) -> int:
    """The sum of the ``m`` largest entries of ``support`` (all of them when None)."""
    return int(np.sort(support)[::-1][:m].sum())


def _enough_references(support: NDArray[np.int64], config: VerifyConfig) -> bool:
    """Whether the supporting references' ``support`` (their explained matches, each at least
    ``min_support_matches``) confirm a place: ``min_supporting_references`` of them, or one with
    ``single_reference_support``."""
    single = config.single_reference_support
    return len(support) >= config.min_supporting_references or (
        single is not None and int(support.max(initial=0)) >= single
    )


def implausible_mount(T_wc: NDArray[np.float64], camera_z: float, config: VerifyConfig) -> str:
    """Why a ground robot's camera cannot have the pose ``T_wc`` (OpenCV camera to W) ("" when it
    can): roll, pitch or height (world z against ``camera_z`` metres, unchecked when nan) outside
    the :class:`VerifyConfig` limits (the "mount" check of :func:`verify_pose`)."""
    roll = _roll_deg(T_wc)
    if config.max_roll_deg is not None and abs(roll) > config.max_roll_deg:
        return f"camera rolled {roll:+.1f} deg"
    pitch = float(np.degrees(camera_yaw_pitch(T_wc)[1]))
    lo, hi = config.pitch_range_deg or (-90.0, 90.0)
    if not lo <= pitch <= hi:
        return f"camera pitched {pitch:.1f} deg down"
    off = float(T_wc[2, 3] - camera_z)
    if config.pose_height_tolerance is not None and abs(off) > config.pose_height_tolerance:
        return f"camera height off by {off:+.2f} m"
    return ""


def rival_poses(
    T_wq: NDArray[np.float64],
    T_wi: NDArray[np.float64],
    out: BackboneOutput,
    support: NDArray[np.int64],
    scale: float,
    averaging: MotionAveragingConfig,
) -> list[NDArray[np.float64]]:
    """Pose hypotheses that compete with ``T_wq``, from the pairs it does not explain
    (``support`` 0; :func:`rival_pairs` also zeroes the pairs it explains in small part): the
    weighted motion average of those pairs (when it succeeds), then each such pair on its own
    (rotation ``R_wi R_iq``, centre along its ray at ``scale`` metres per backbone unit)."""
    rest = (out.confidence > 0) & (support == 0)
    if not rest.any():
        return []
    rivals = []
    if rest.sum() >= 2:
        motion = average_motion(T_wi, out.T_qi, np.where(rest, out.confidence, 0.0), averaging)
        if motion.ok:
            rivals.append(motion.T_wq)
    T_iq = out.T_iq
    for i in np.flatnonzero(rest):
        R = T_wi[i, :3, :3] @ T_iq[i, :3, :3]
        rivals.append(make_pose(R, pair_centre(T_wi[i], T_iq[i], scale)))
    return rivals


def rival_pairs(
    support: NDArray[np.int64],
    T_wi: NDArray[np.float64],
    out: BackboneOutput,
    camera: PinholeCamera,
    config: VerifyConfig,
    own: NDArray[np.int64] | None = None,
) -> NDArray[np.int64]:
    """``support`` (k,) of a pose (0 where under ``min_support_matches``), also 0 where the pose
    explains fewer than ``rival_claim_ratio`` of the matches the pair's own relative pose explains
    (:func:`pair_support`; ``own`` when already computed): the pairs :func:`rival_poses` makes
    rivals of."""
    support = np.where(support >= config.min_support_matches, support, 0)
    if config.rival_claim_ratio is None:
        return support
    own = pair_support(T_wi, out, camera, config) if own is None else own
    weak = support < config.rival_claim_ratio * own
    return np.where(weak, 0, support)


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


def pooled_pairs(
    refs: NDArray[np.int64], out: BackboneOutput, other_refs: NDArray[np.int64], other: BackboneOutput
) -> tuple[NDArray[np.int64], BackboneOutput]:
    """The pairs of two rounds over the same query as one set for verification: ``refs`` and
    ``out``, then the pairs of ``other`` (references ``other_refs``) whose reference is not in
    ``refs``. The second round chooses references around its own hypotheses, so around an aliased
    place all of them agree with it; the first round's pairs with the true place must still
    count. Per-pixel fields (depths) are ``out``'s; ``reference_depths`` is dropped."""
    new = ~np.isin(other_refs, refs)
    if not new.any():
        return refs, out
    matches = None
    if out.matches is not None and other.matches is not None:
        matches = list(out.matches) + [m for m, n in zip(other.matches, new, strict=True) if n]
    pooled = replace(
        out,
        T_qi=np.concatenate([out.T_qi, other.T_qi[new]]),
        confidence=np.concatenate([out.confidence, other.confidence[new]]),
        n_matches=np.concatenate([out.n_matches, other.n_matches[new]]),
        scale_valid=np.concatenate([out.scale_valid, other.scale_valid[new]]),
        reference_depths=None,
        matches=matches,
    )
    return np.concatenate([refs, other_refs[new]]).astype(np.int64), pooled


def round_rank(out: BackboneOutput, motion: MotionResult) -> tuple[bool, int, float]:
    """Order of two rounds' outcomes: a pose, then more consistent references, then the best pair."""
    n_inliers = int(motion.inliers.sum()) if motion.ok else 0
    return motion.ok, n_inliers, float(out.confidence.max(initial=0.0))


def second_round_references(
    refs: NDArray[np.int64],
    out: BackboneOutput,
    motion: MotionResult,
    similarity: NDArray[np.float64],
    T_w: NDArray[np.float64],
    config: VerifyConfig,
    *,
    k: int,
    consensus_deg: float,
    pair_scale: Callable[[NDArray[np.float64]], float | None] | None,
) -> NDArray[np.int64]:
    """References of the second round (empty: none needed or none found).

    ``refs``, ``out``, ``motion``: the first round (database indices, backbone output, weighted
    motion averaging); ``similarity`` (M,) and ``T_w`` (M, 4, 4): the database's retrieval scores
    and ``T_wi``; ``k``: references per round; ``consensus_deg``: the rotation consensus of motion
    averaging. Hypotheses: the averaged pose (when ok), then the most confident pairs' poses
    (rotation ``R_wi R_iq``; centre along the pair's ray at ``pair_scale(T)`` metres per backbone
    unit -- the ground scale at the calibrated camera height, None when not found or without
    scale recovery -- else the reference centre), distinct ones only (farther than the radius or
    the consensus angle from the others). Each hypothesis' pair is kept (the averaged pose keeps
    its inliers; up to k / 2 kept), the rest are new database images around the hypotheses
    (:func:`pose_guided_references`). Without any hypothesis (no pair passed), the k most similar
    database images not tried yet.
    """
    below = config.second_round_below_inliers
    n_inliers = int(motion.inliers.sum()) if motion.ok else 0
    if below is None or n_inliers >= below:
        return np.zeros(0, np.int64)
    hypotheses: list[NDArray[np.float64]] = []
    keep: list[int] = []
    if motion.ok:
        hypotheses.append(motion.T_wq)
        keep += [int(i) for i in refs[motion.inliers]]
    consensus = np.deg2rad(consensus_deg)
    for j in np.argsort(-out.confidence, kind="stable"):
        if out.confidence[j] <= 0 or len(hypotheses) >= config.second_round_hypotheses + int(motion.ok):
            break
        T_wi = T_w[refs[j]]
        T = make_pose(T_wi[:3, :3] @ out.T_iq[j, :3, :3], T_wi[:3, 3])
        scale = pair_scale(T) if pair_scale is not None else None
        if scale is not None:
            T[:3, 3] = pair_centre(T_wi, out.T_iq[j], scale)
        if any(
            np.linalg.norm(T[:3, 3] - h[:3, 3]) <= config.second_round_radius
            and rotation_angle(T[:3, :3], h[:3, :3]) <= consensus
            for h in hypotheses
        ):
            continue
        hypotheses.append(T)
        keep.append(int(refs[j]))
    if not hypotheses:
        untried = np.argsort(-similarity, kind="stable")
        return untried[~np.isin(untried, refs)][:k].astype(np.int64)
    keep = list(dict.fromkeys(keep))[: max(1, k // 2)]
    new = pose_guided_references(
        T_w,
        np.array(hypotheses),
        k - len(keep),
        exclude=refs,
        radius=config.second_round_radius,
        max_angle_deg=config.second_round_max_angle_deg,
    )
    if len(new) == 0:
        return np.zeros(0, np.int64)
    return np.concatenate([np.array(keep, np.int64), new])


def prior_support_floor(prior: PoseGate, config: VerifyConfig) -> int:
    """The matches a pose placed inside the ``prior`` (:func:`prior_poses`) must have explained,
    together, by references of at least ``min_support_matches`` each: ``prior_support_per_m`` per
    metre of the prior's radius, at most ``min_total_support`` (the floor without a prior; a pose is
    searched over the prior's disc, and the tighter the disc the fewer places a stray support can
    come from). ``min_total_support`` when ``prior_support_per_m`` is None, 0 when both are."""
    full = config.min_total_support or 0
    if config.prior_support_per_m is None:
        return full
    return min(full, int(np.ceil(config.prior_support_per_m * prior.max_distance)))


def prior_pairs(T_wi: NDArray[np.float64], out: BackboneOutput, prior: PoseGate) -> NDArray[np.bool_]:
    """(k,) the confident pairs whose own pose agrees with the ``prior``: the heading of
    ``R_wi R_iq`` within the prior's yaw bound, and the ray from the reference centre towards the
    query (``R_wi t_iq``) passing within its distance of the prior's position (horizontally, in
    front of the reference). ``T_wi`` (k, 4, 4): the references' poses."""
    x, y, yaw = np.asarray(prior.pose, float)
    agree = np.zeros(len(T_wi), bool)
    for i in np.flatnonzero(out.confidence > 0):
        R = T_wi[i, :3, :3] @ out.T_iq[i, :3, :3]
        if abs(wrap_angle(camera_yaw_pitch(make_pose(R, np.zeros(3)))[0] - yaw)) > prior.max_yaw:
            continue
        d = (T_wi[i, :3, :3] @ out.T_iq[i, :3, 3])[:2]
        if not np.linalg.norm(d) > 0:
            continue
        d = d / np.linalg.norm(d)
        to_prior = np.array([x, y]) - T_wi[i, :2, 3]
        along = float(to_prior @ d)
        agree[i] = along > 0 and float(np.linalg.norm(to_prior - along * d)) <= prior.max_distance
    return agree


def prior_poses(
    T_wi: NDArray[np.float64],
    out: BackboneOutput,
    camera: PinholeCamera,
    prior: PoseGate,
    camera_z: float,
    config: VerifyConfig,
) -> list[NDArray[np.float64]]:
    """Pose hypotheses inside the ``prior`` for a frame motion averaging could not place: per
    confident pair (most confident first, up to ``prior_hypotheses``) whose own rotation
    ``R_wi R_iq`` a ground robot's camera could have (roll within ``prior_max_roll_deg``, the
    mount's pitch) with its heading within the prior's yaw bound, that rotation at the camera
    position within the prior (height ``camera_z``, metres, W) whose matches with all references
    the pose explains best (:func:`reference_support`, summed): a grid of ``prior_grid_m`` over the
    prior's disc, then a quarter of it around the best. The pairs' relative translations are the
    weak part of a short baseline (their rotations are right to a degree when their translation
    directions are 50-70 deg off); the matches themselves still fit the true pose. Each
    hypothesis must still be confirmed by :func:`verify_pose`.
    """
    x, y, yaw = np.asarray(prior.pose, float)
    step = config.prior_grid_m
    n = int(np.ceil(prior.max_distance / step))
    offsets = np.stack(np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1)), -1).reshape(-1, 2) * step
    offsets = offsets[np.linalg.norm(offsets, axis=1) <= prior.max_distance]
    fine = np.stack(np.meshgrid(np.arange(-2, 3), np.arange(-2, 3)), -1).reshape(-1, 2) * (step / 4)

    def best(R: NDArray[np.float64], centre: NDArray[np.float64], grid: NDArray[np.float64]):
        poses = [make_pose(R, np.r_[centre + o, camera_z]) for o in grid]
        poses = [T for T in poses if prior.admits(T)]
        scores = [int(reference_support(T, T_wi, out, camera, config).sum()) for T in poses]
        return poses[int(np.argmax(scores))] if poses else None

    hypotheses: list[NDArray[np.float64]] = []
    for i in np.argsort(-out.confidence, kind="stable"):
        if out.confidence[i] <= 0 or len(hypotheses) >= config.prior_hypotheses:
            break
        R = T_wi[i, :3, :3] @ out.T_iq[i, :3, :3]
        T = make_pose(R, np.array([x, y, camera_z]))
        if abs(_roll_deg(T)) > config.prior_max_roll_deg or implausible_mount(T, camera_z, config):
            continue
        if not prior.admits(T):
            continue
        if any(rotation_angle(R, h[:3, :3]) < np.deg2rad(1.0) for h in hypotheses):
            continue
        coarse = best(R, np.array([x, y]), offsets)
        refined = best(R, coarse[:2, 3], fine) if coarse is not None else None
        if refined is not None:
            hypotheses.append(refined)
    return hypotheses


def refine_pose(
    T_wq: NDArray[np.float64],
    T_wi: NDArray[np.float64],
    matches: Sequence[NDArray[np.floating]],
    camera: PinholeCamera,
    config: VerifyConfig,
    *,
    max_shift: float,
    max_height: float = 0.05,
    max_rotation_deg: float = 1.5,
) -> NDArray[np.float64]:
    """``T_wq`` moved to the pose whose epipolar geometry with the references ``T_wi`` (k, 4, 4)
    best explains their ``matches`` (per reference (m_i, 4) pixels, :attr:`BackboneOutput.matches`):
    robust (Cauchy, ``max_epipolar_error_px``) least squares of the Sampson distances over all
    references at once, rotation and metric position (the references' known poses fix the scale),
    within ``max_rotation_deg`` about each axis, ``max_shift`` metres horizontally and
    ``max_height`` vertically of ``T_wq`` (a pose refined freely can slide to a wrong one that a
    repeated texture supports as well).
    A pose a few centimetres or a degree off (from the prior, or one pair's rotation) explains few
    of the matches within the verification's 2 pixels; refined, the references that see the place
    explain it. Returns ``T_wq`` unchanged when fewer than 8 matches are given."""
    m = [np.asarray(a, float).reshape(-1, 4) for a in matches]
    ref = np.concatenate([np.full(len(a), i) for i, a in enumerate(m)]).astype(int)
    if len(ref) < 8:
        return T_wq
    uv = np.concatenate(m)
    K_inv = np.linalg.inv(camera.K)
    f = float(np.sqrt(camera.K[0, 0] * camera.K[1, 1]))
    x_q = np.c_[uv[:, :2], np.ones(len(uv))] @ K_inv.T
    x_i = np.c_[uv[:, 2:], np.ones(len(uv))] @ K_inv.T
    R_iw = np.transpose(T_wi[:, :3, :3], (0, 2, 1))
    R0 = T_wq[:3, :3]

    def pose(p: NDArray[np.float64]) -> NDArray[np.float64]:
        return make_pose(R0 @ Rotation.from_rotvec(p[:3]).as_matrix(), p[3:])

    def residuals(p: NDArray[np.float64]) -> NDArray[np.float64]:
        T = pose(p)
        R = R_iw @ T[:3, :3]  # (k, 3, 3) R_iq
        t = np.einsum("kij,kj->ki", R_iw, T[:3, 3] - T_wi[:, :3, 3])
        t = t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-9)
        tx = np.zeros((len(t), 3, 3))
        tx[:, 0, 1], tx[:, 0, 2], tx[:, 1, 2] = -t[:, 2], t[:, 1], -t[:, 0]
        tx[:, 1, 0], tx[:, 2, 0], tx[:, 2, 1] = t[:, 2], -t[:, 1], t[:, 0]
        E = (tx @ R)[ref]
        Ex_q = np.einsum("mij,mj->mi", E, x_q)
        Etx_i = np.einsum("mji,mj->mi", E, x_i)
        num = np.einsum("mi,mi->m", x_i, Ex_q)
        den = Ex_q[:, 0] ** 2 + Ex_q[:, 1] ** 2 + Etx_i[:, 0] ** 2 + Etx_i[:, 1] ** 2
        return f * num / np.sqrt(np.maximum(den, 1e-18))

    p0 = np.r_[np.zeros(3), T_wq[:3, 3]]
    step = np.r_[np.full(3, np.deg2rad(max_rotation_deg)), max_shift, max_shift, max_height]
    fit = least_squares(
        residuals,
        p0,
        bounds=(p0 - step, p0 + step),
        loss="cauchy",
        f_scale=config.max_epipolar_error_px,
        max_nfev=50,
    )
    return pose(fit.x)


def slide_on_ray(
    T_wq: NDArray[np.float64],
    T_wi: NDArray[np.float64],
    out: BackboneOutput,
    weights: NDArray[np.float64],
    camera: PinholeCamera,
    config: VerifyConfig,
) -> tuple[NDArray[np.float64], float] | None:
    """``T_wq`` moved along the ray of the pair its position rests on, to where the other
    references' matches confirm it, and the factor its distance to that pair's reference grew
    by (what the scale that placed it was off by); None when nothing moves (``ray_slide_share``
    None, no pair with at least that share of the translation ``weights`` (k,), or no place
    gains the support).

    A position that one pair's ray carries is only as right as the scale that placed it along
    that ray (ground or rays), while the references that ray does not pass through see the
    distance: their epipolar support (:func:`epipolar_support`, summed: a threshold per
    reference would make a step where one crosses it) peaks at the true place. Positions within
    ``ray_slide_max_shift`` metres of ``T_wq`` on the ray (steps of 2 cm, then 5 mm about the
    best, the middle of equal ones), the rotation kept; the best counts when it gains at least
    ``ray_slide_gain`` of ``T_wq``'s support and reaches ``min_support_matches`` (fewer are stray
    matches, not a reference that sees the place)."""
    share = config.ray_slide_share
    w = np.asarray(weights, float)
    if share is None or out.matches is None or len(w) != len(T_wi) or not w.sum() > 0:
        return None
    j = int(np.argmax(w))
    ray = T_wi[j][:3, :3] @ out.T_iq[j][:3, 3]
    if w[j] < share * w.sum() or not np.linalg.norm(ray) > 0:
        return None
    ray, centre = ray / np.linalg.norm(ray), T_wi[j][:3, 3]
    others = np.flatnonzero(np.arange(len(w)) != j)
    matches = [out.matches[i] for i in others]

    def support(T: NDArray[np.float64]) -> int:
        return int(epipolar_support(T, T_wi[others], matches, camera, config.max_epipolar_error_px).sum())

    def at(distance: float) -> NDArray[np.float64]:
        T = T_wq.copy()
        T[:3, 3] = centre + distance * ray
        return T

    now = float((T_wq[:3, 3] - centre) @ ray)
    reach = config.ray_slide_max_shift
    best_d, best = now, -1
    for step, span in ((0.02, reach), (0.005, 0.02)):
        d = best_d + np.arange(-span, span + step / 2, step)
        d = d[(d > 0) & (np.linalg.norm(centre + d[:, None] * ray - T_wq[:3, 3], axis=1) <= reach)]
        if len(d) == 0:
            return None
        scores = np.array([support(at(x)) for x in d])
        best = int(scores.max())
        best_d = float(np.median(d[scores == best]))  # the middle of a plateau of equal support
    if best < max(support(T_wq) * (1.0 + config.ray_slide_gain), config.min_support_matches):
        return None
    before = float(np.linalg.norm(T_wq[:3, 3] - centre))
    return at(best_d), best_d / before


def single_pair_fallback(
    refs: NDArray[np.int64],
    out: BackboneOutput,
    T_w: NDArray[np.float64],
    averaging: MotionAveragingConfig,
    config: VerifyConfig,
) -> MotionResult | None:
    """The pose of the most confident pair alone (a ``single reference`` motion result at backbone
    scale, to be placed with the ground scale), or None when no pair reaches
    ``single_fallback_confidence`` (or the fallback is off)."""
    thr = config.single_fallback_confidence
    if thr is None or float(out.confidence.max(initial=0.0)) < thr:
        return None
    single = replace(averaging, method="single", single_reference="confidence")
    return average_motion(T_w[refs], out.T_qi, out.confidence, single, scale_valid=out.scale_valid)
