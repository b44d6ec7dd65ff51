"""Recovery: what :meth:`~vgpnav_env.perception.pipeline.Perceiver.perceive` tries when the paper's
stages give no verified pose, as ONE ordered list of small strategies (:data:`RECOVERY`).

Each strategy is a function of the perceiver, the frame (:class:`~vgpnav_env.perception.pipeline.
Frame`) and the current outcome that returns a better outcome, or None when it does not apply or
finds nothing. Strategies of :attr:`Phase.POSE` act on stages 1-3's outcome (references, backbone
output, motion averaging) before scale recovery and verification; those of :attr:`Phase.RESULT`
on the verified -- or lost -- frame. Every pose a strategy proposes is verified by the images
(:func:`~vgpnav_env.perception.verify.assess`). The geometry they use is here too:
:func:`second_round_references`, :func:`single_pair_fallback`, :func:`prior_poses`,
:func:`slide_on_ray`; their settings are :class:`RecoveryConfig` (``PerceptionConfig.recovery``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from enum import StrEnum
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from vgpnav_env.geometry import make_pose, rotation_angle
from vgpnav_env.perception.backbones.base import BackboneOutput
from vgpnav_env.perception.motion_averaging import (
    MotionAveragingConfig,
    MotionResult,
    average_motion,
    pair_centre,
)
from vgpnav_env.perception.retrieval import pose_guided_references
from vgpnav_env.perception.verify import (
    LostReason,
    Pairs,
    PoseGate,
    VerifyConfig,
    assess,
    check_height,
    check_scale,
    epipolar_support,
    implausible_mount,
    plausible_scale,
    prior_pairs,
    reference_support,
    refine_pose,
)
from vgpnav_env.perception.verify.verdict import roll_deg

if TYPE_CHECKING:
    from vgpnav_env.perception.backbones.base import Privileged
    from vgpnav_env.perception.pipeline import Clock, Localization, MetricPose, Perceiver, PerceptionResult


@dataclass(frozen=True)
class RecoveryConfig:
    """Settings of the recovery strategies (:data:`RECOVERY`); None switches one off. Distances in
    metres, angles in degrees.

    Attributes:
        second_round_below_inliers: with fewer consistent references than this (a failed pose
            counts 0) a second round verifies references chosen around the first round's pose
            hypotheses; the round with more consistent references wins (None: one round).
        second_round_hypotheses: at most this many distinct pose hypotheses seed the second round.
        second_round_radius: its database cameras lie within this distance of a hypothesis ...
        second_round_max_angle_deg: ... and within this angle of its heading.
        single_fallback_confidence: when motion averaging fails, a pair at least this confident
            gives the pose alone, placed with the ground scale (needs scale recovery).
        prior_hypotheses: a frame lost inside a prior gets up to this many pose hypotheses there
            (:func:`prior_poses`) ...
        prior_grid_m: ... whose positions are searched on a grid of this step.
        prior_support_per_m: a pose placed inside the prior needs this many supporting matches per
            metre of the prior's radius, at most ``VerifyConfig.min_total_support``
            (:func:`prior_support_floor`; None: ``min_total_support``).
        ray_slide_share: a verified pose whose position one pair's ray carries (at least this
            share of the translation weight) may slide along that ray (:func:`slide_on_ray`;
            None: never) ...
        ray_slide_gain: ... to where the other references explain this fraction more matches ...
        ray_slide_max_shift: ... by at most this distance.

    Where the defaults came from: ``benchmarks/history/tuning.md``.
    """

    second_round_below_inliers: int | None = 3
    second_round_hypotheses: int = 2
    second_round_radius: float = 1.5
    second_round_max_angle_deg: float = 35.0
    single_fallback_confidence: float | None = 0.15
    prior_hypotheses: int = 3
    prior_grid_m: float = 0.08
    prior_support_per_m: float | None = 350.0
    ray_slide_share: float | None = 0.55
    ray_slide_gain: float = 0.1
    ray_slide_max_shift: float = 0.3

    def __post_init__(self) -> None:
        if self.second_round_hypotheses < 1 or self.second_round_radius <= 0:
            raise ValueError("need second_round_hypotheses >= 1 and second_round_radius > 0 m")
        if self.prior_support_per_m is not None and not self.prior_support_per_m > 0:
            raise ValueError(f"prior_support_per_m must be > 0 or None, got {self.prior_support_per_m}")
        if self.ray_slide_share is not None and not 0 < self.ray_slide_share <= 1:
            raise ValueError(f"ray_slide_share must be in (0, 1] or None, got {self.ray_slide_share}")
        if self.ray_slide_gain < 0 or not self.ray_slide_max_shift > 0:
            raise ValueError(
                f"need ray_slide_gain >= 0 and ray_slide_max_shift > 0 m, got "
                f"{self.ray_slide_gain}, {self.ray_slide_max_shift}"
            )


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
    config: RecoveryConfig,
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


def slide_on_ray(
    T_wq: NDArray[np.float64], pairs: Pairs, weights: NDArray[np.float64], config: RecoveryConfig
) -> tuple[NDArray[np.float64], float] | None:
    """``T_wq`` moved along the ray of the pair (of the query's ``pairs``) its position rests on, to
    where the other references' matches confirm it, and the factor its distance to that pair's reference grew
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
    T_wi, out, verify = pairs.T_wi, pairs.out, pairs.config
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
    error_px = verify.max_epipolar_error_px

    def support(T: NDArray[np.float64]) -> int:
        return int(epipolar_support(T, T_wi[others], matches, pairs.camera, error_px).sum())

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
    if best < max(support(T_wq) * (1.0 + config.ray_slide_gain), verify.min_support_matches):
        return None
    before = float(np.linalg.norm(T_wq[:3, 3] - centre))
    return at(best_d), best_d / before


def single_pair_fallback(
    pairs: Pairs, averaging: MotionAveragingConfig, config: RecoveryConfig
) -> MotionResult | None:
    """The pose of the most confident of the query's ``pairs`` alone (a ``single reference`` motion
    result at backbone scale, to be placed with the ground scale), or None when no pair reaches
    ``single_fallback_confidence`` (or the fallback is off)."""
    out, thr = pairs.out, config.single_fallback_confidence
    if thr is None or float(out.confidence.max(initial=0.0)) < thr:
        return None
    single = replace(averaging, method="single", single_reference="confidence")
    return average_motion(pairs.T_wi, out.T_qi, out.confidence, single, scale_valid=out.scale_valid)


@dataclass(frozen=True)
class Frame:
    """One :meth:`~vgpnav_env.perception.pipeline.Perceiver.perceive` call's inputs: the RGB image,
    the simulated backbone's ``privileged`` data, the caller's ``gate``, ``predicted`` camera pose
    (tracking) and ``prior`` (a state estimate's), and the call's ``clock``."""

    rgb: NDArray[np.uint8]
    privileged: Privileged | None
    gate: PoseGate | None
    predicted: NDArray[np.float64] | None
    prior: PoseGate | None
    clock: Clock


@dataclass(frozen=True)
class Attempt:
    """One attempt at a frame: its ``result`` (not fused), metric ``points_w`` (None when lost) and,
    when it went through stages 1-4, its ``loc`` and ``pose``; ``rival``: the prior picked a rival
    of the averaged pose."""

    result: PerceptionResult
    points_w: NDArray[np.float64] | None
    loc: Localization | None = None
    pose: MetricPose | None = None
    rival: bool = False


@dataclass(frozen=True)
class Outcome:
    """What :attr:`Phase.RESULT` strategies see and return: the current ``attempt`` and the ``lost``
    attempts (newest first) a prior may still place."""

    attempt: Attempt
    lost: tuple[Attempt, ...] = ()


class Phase(StrEnum):
    """Where a recovery strategy acts."""

    POSE = "pose"  # on stages 1-3's outcome (a weak or failed round), before scale and verification
    RESULT = "result"  # on the frame after verification (lost, or verified and refinable)


@dataclass(frozen=True)
class Strategy:
    """One recovery strategy: its ``name``, ``phase`` and function ``run`` (perceiver, frame,
    outcome) -> a better outcome or None; the outcome is a
    :class:`~vgpnav_env.perception.pipeline.Localization` in :attr:`Phase.POSE`, an
    :class:`~vgpnav_env.perception.pipeline.Outcome` in :attr:`Phase.RESULT`."""

    name: str
    phase: Phase
    run: Callable[[Perceiver, Frame, Any], Any]


def second_round(perceiver: Perceiver, frame: Frame, loc: Localization) -> Localization | None:
    """With fewer consistent references than ``second_round_below_inliers`` (weighted motion
    averaging only), a second backbone round over :func:`second_round_references`; the better
    round (:func:`round_rank`) is kept, the other's pairs stay for verification
    (``Localization.other``). None: not needed, or no references."""
    cfg = perceiver.config
    if cfg.averaging.method != "weighted" or loc.backbone is None or loc.similarity is None:
        return None
    out, motion, refs = loc.backbone, loc.motion, loc.references
    with frame.clock.stage("retrieval"):
        second = second_round_references(
            refs, out, motion, loc.similarity, perceiver.database.poses, cfg.recovery,
            k=cfg.retrieval.k, consensus_deg=cfg.averaging.consensus_deg,
            pair_scale=(lambda T: perceiver.calibrated_scale(out, T)) if cfg.scale.enabled else None,
        )  # fmt: skip
    if len(second) == 0:
        return None
    out2, motion2 = perceiver.round(frame, second, loc.guide)
    if round_rank(out2, motion2) > round_rank(out, motion):
        return perceiver.conclude(replace(loc, references=second, other=(refs, out)), out2, motion2)
    return perceiver.conclude(replace(loc, other=(second, out2)), out, motion)


def prior_consensus(perceiver: Perceiver, frame: Frame, loc: Localization) -> Localization | None:
    """A failed motion averaging redone over the pairs that agree with the frame's ``prior``
    (:func:`prior_pairs`, at least two); None when there is no prior or it fails too."""
    prior = frame.prior
    if loc.ok or prior is None or loc.motion is None or loc.n_confident_pairs == 0:
        return None
    cfg, out = perceiver.config, loc.backbone
    T_wi = perceiver.database.poses[loc.references]
    with frame.clock.stage("motion_averaging"):
        agree = prior_pairs(T_wi, out, prior)
        if agree.sum() < 2:
            return None
        confidence = np.where(agree, out.confidence, 0.0)
        motion = average_motion(T_wi, out.T_qi, confidence, cfg.averaging, scale_valid=out.scale_valid)
        motion = check_height(motion, perceiver.anchor, cfg.camera_height, cfg.verify)
    if not motion.ok:
        return None
    return replace(loc, motion=motion, reason="", detail=f"pairs agreeing with the prior after: {loc.detail}")


def single_pair(perceiver: Perceiver, frame: Frame, loc: Localization) -> Localization | None:
    """A failed motion averaging replaced by the most confident pair alone
    (:func:`single_pair_fallback`, placed with the ground scale later); None without scale
    recovery or without a confident pair."""
    if loc.ok or loc.motion is None or loc.n_confident_pairs == 0 or not perceiver.config.scale.enabled:
        return None
    cfg = perceiver.config
    with frame.clock.stage("motion_averaging"):
        pairs = perceiver.pairs(loc.references, loc.backbone)
        motion = single_pair_fallback(pairs, cfg.averaging, cfg.recovery)
    if motion is None:
        return None
    return replace(loc, motion=motion, reason="", detail=f"single-pair fallback after: {loc.detail}")


def prior_retry(perceiver: Perceiver, frame: Frame, outcome: Outcome) -> Outcome | None:
    """A frame lost with a ``prior`` (not by the prior itself) once the ground is anchored gets one
    more attempt: global references lost -> references around the prior's pose; a tracked attempt
    without database cameras near the predicted pose -> global references (a tracked attempt that
    ran its backbone gets none). Kept when it localizes or ran its backbone."""
    first = outcome.attempt.result
    if frame.prior is None or first.localized or not perceiver.anchor.initialized:
        return None
    if first.reason == LostReason.INCONSISTENT_MOTION:
        return None
    if frame.predicted is not None and first.backbone is not None:
        return None
    around = perceiver.prior_camera(frame.prior) if frame.predicted is None else None
    again = perceiver.attempt(frame, around)
    if not (again.result.localized or again.result.backbone is not None):
        return None
    lost = (again, *outcome.lost) if again.result.reason != LostReason.INCONSISTENT_MOTION else ()
    return replace(outcome, attempt=again, lost=lost)


def prior_placement(perceiver: Perceiver, frame: Frame, outcome: Outcome) -> Outcome | None:
    """A frame still lost with a ``prior``: the first of its lost attempts (newest first) whose pairs
    give a pose inside the prior that the images confirm (:func:`place_on_prior`)."""
    if frame.prior is None or outcome.attempt.result.localized:
        return None
    for lost in outcome.lost:
        with frame.clock.stage("verification"):
            placed = place_on_prior(perceiver, lost.result, frame.prior, frame.gate)
        if placed is not None:
            return replace(outcome, attempt=placed, lost=())
    return None


def slide(perceiver: Perceiver, frame: Frame, outcome: Outcome) -> Outcome | None:
    """A pose verified inside the ``prior`` (not a rival the prior picked, not the one anchoring the
    ground) moved along the ray of the pair its position rests on (:func:`slide_on_ray`), its scale
    corrected by the same factor, when the images verify it there and the prior and the gate admit
    it."""
    attempt, prior = outcome.attempt, frame.prior
    loc, pose = attempt.loc, attempt.pose
    if prior is None or not attempt.result.localized or loc is None or pose is None:
        return None
    if attempt.rival or pose.anchor is not None:
        return None
    with frame.clock.stage("verification"):
        pairs = perceiver.pairs(loc.references, loc.backbone)
        moved = slide_on_ray(pose.T_wc, pairs, loc.motion.weights, perceiver.config.recovery)
        if moved is None:
            return None
        T, factor = moved
        if any(g is not None and not g.admits(T) for g in (prior, frame.gate)):
            return None
        slid = replace(pose, T_wc=T, scale=replace(pose.scale, scale=pose.scale.scale * factor))
        T_checked, verdict = perceiver.verify(loc, slid, prior)
    if T_checked is not T or not verdict.ok:
        return None
    points = perceiver.points(loc, T, slid.scale)
    result = replace(
        attempt.result, T_wc=T, points_w=points.astype(np.float32), scale=slid.scale.scale,
        verdict=verdict, confidence=verdict.confidence,
    )  # fmt: skip
    return replace(outcome, attempt=replace(attempt, result=result, points_w=points, pose=slid))


def prior_support_floor(prior: PoseGate, verify: VerifyConfig, config: RecoveryConfig) -> int:
    """The matches a pose placed inside the ``prior`` (:func:`prior_poses`) must have explained,
    together, by references of at least ``min_support_matches`` each: ``prior_support_per_m`` per
    metre of the prior's radius, at most ``min_total_support`` (the floor without a prior; a pose is
    searched over the prior's disc, and the tighter the disc the fewer places a stray support can
    come from). ``min_total_support`` when ``prior_support_per_m`` is None, 0 when both are."""
    full = verify.min_total_support or 0
    if config.prior_support_per_m is None:
        return full
    return min(full, int(np.ceil(config.prior_support_per_m * prior.max_distance)))


def prior_poses(
    pairs: Pairs, prior: PoseGate, camera_z: float, config: RecoveryConfig
) -> list[NDArray[np.float64]]:
    """Pose hypotheses inside the ``prior`` for a frame motion averaging could not place, from the
    query's ``pairs``: per
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
    T_wi, out, verify = pairs.T_wi, pairs.out, pairs.config
    x, y, yaw = np.asarray(prior.pose, float)
    step = config.prior_grid_m
    n = int(np.ceil(prior.max_distance / step))
    offsets = np.stack(np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1)), -1).reshape(-1, 2) * step
    offsets = offsets[np.linalg.norm(offsets, axis=1) <= prior.max_distance]
    fine = np.stack(np.meshgrid(np.arange(-2, 3), np.arange(-2, 3)), -1).reshape(-1, 2) * (step / 4)

    def best(R: NDArray[np.float64], centre: NDArray[np.float64], grid: NDArray[np.float64]):
        poses = [make_pose(R, np.r_[centre + o, camera_z]) for o in grid]
        poses = [T for T in poses if prior.admits(T)]
        if not poses:
            return None
        return poses[int(np.argmax(reference_support(np.stack(poses), pairs).sum(axis=1)))]

    hypotheses: list[NDArray[np.float64]] = []
    for i in np.argsort(-out.confidence, kind="stable"):
        if out.confidence[i] <= 0 or len(hypotheses) >= config.prior_hypotheses:
            break
        R = T_wi[i, :3, :3] @ out.T_iq[i, :3, :3]
        T = make_pose(R, np.array([x, y, camera_z]))
        if abs(roll_deg(T)) > verify.prior_max_roll_deg or implausible_mount(T, camera_z, verify):
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


#: The recovery strategies in the order :meth:`~vgpnav_env.perception.pipeline.Perceiver.perceive`
#: tries them (each phase in turn; a strategy that returns None leaves the outcome as it was).
RECOVERY: tuple[Strategy, ...] = (
    Strategy("second round", Phase.POSE, second_round),
    Strategy("prior consensus", Phase.POSE, prior_consensus),
    Strategy("single pair", Phase.POSE, single_pair),
    Strategy("prior retry", Phase.RESULT, prior_retry),
    Strategy("prior placement", Phase.RESULT, prior_placement),
    Strategy("slide", Phase.RESULT, slide),
)


def place_on_prior(
    perceiver: Perceiver, lost: PerceptionResult, prior: PoseGate, gate: PoseGate | None
) -> Attempt | None:
    """A ``lost`` frame placed inside the ``prior`` (:func:`prior_poses`) when :func:`assess`
    with the prior confirms that pose with at least ``min_supporting_references`` (and 2)
    references that explain :func:`prior_support_floor` matches together: the strongest such
    pose, localized and marked :attr:`PerceptionResult.prior_placed`, and its metric points;
    else None. Its scale is the ground's, checked against the supporting pairs' (their distance
    to the pose over their backbone translation, median); without a ground peak the pose comes
    with no points."""
    out, refs = lost.backbone, lost.references
    if out is None or out.matches is None or not perceiver.anchor.initialized:
        return None  # without matches a reference's support is a 10 deg test: no placement
    if not (out.confidence > 0).any():
        return None
    cfg, v = perceiver.config, perceiver.config.verify
    pairs = perceiver.pairs(refs, out)
    T_wi = pairs.T_wi
    camera_z = float(perceiver.anchor.z_ground) + cfg.camera_height
    hypotheses = prior_poses(pairs, prior, camera_z, cfg.recovery)
    if not hypotheses:
        return None
    baseline = np.linalg.norm(out.T_iq[:, :3, 3], axis=1)
    best = None
    refined = [refine_pose(T, pairs, max_shift=prior.max_distance) for T in hypotheses]
    hypotheses += [T for T in refined if prior.admits(T)]
    for T in hypotheses:
        distance = np.linalg.norm(T_wi[:, :3, 3] - T[:3, 3], axis=1)
        support = reference_support(T, pairs)
        usable = (support >= v.min_support_matches) & out.scale_valid & (baseline > 0) & (out.confidence > 0)
        if not usable.any():
            continue
        pair_scale = float(np.median(distance[usable] / baseline[usable]))
        verdict = assess(
            T, pairs, scale=pair_scale, averaging=cfg.averaging, camera_z=camera_z, prior=prior
        ).verdict
        enough = verdict.n_supporting >= max(2, v.min_supporting_references)
        if not (verdict.ok and enough) or (best is not None and verdict.strength <= best[3].strength):
            continue
        # The prior says where, not whether: the images must give the pose its support, the more
        # the wider the prior (prior_support_floor). The verdict inside the prior has already waived
        # rivals outside it, the share and a wall's plane (its aliases lie elsewhere).
        if verdict.strength < prior_support_floor(prior, v, cfg.recovery):
            continue
        best = T, pair_scale, float(out.confidence[usable].sum()), verdict
    if best is None:
        return None
    T, pair_scale, weight, verdict = best
    if gate is not None and not gate.admits(T):
        return None
    ground = perceiver.ground(out, T, perceiver.anchor.expected_height_b(T, pair_scale))
    scale = perceiver.anchor.scale_for(T, ground, fallback_scale=pair_scale)
    scale = check_scale(scale, pair_scale, v, weight, ground)
    scale = plausible_scale(scale, perceiver.median_depth(out), v)
    if not scale.ok:
        return None
    # A placed pose without the ground's scale has no metric depth to map (the supporting
    # pairs' scale puts its points decimetres to metres off).
    ground_scale = scale.source == "ground"
    points_w = perceiver.metric_points(out, T, scale.scale) if ground_scale else np.zeros((0, 3))
    detail = f"placed inside the prior after {lost.reason}: {lost.detail}"
    if not ground_scale:
        detail = f"{detail}; no ground scale, no points"
    result = replace(
        lost,
        status="localized",
        reason="",
        T_wc=T,
        points_w=points_w.astype(np.float32),
        scale=scale.scale,
        scale_source=scale.source,
        z_ground=float(perceiver.anchor.z_ground),
        ground=ground,
        detail=detail,
        verdict=replace(verdict, by_prior=True),
        confidence=verdict.confidence,
    )
    return Attempt(result, points_w)
