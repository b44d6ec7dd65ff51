"""Recovery: what :meth:`~vgpnav_env.perception.pipeline.Perceiver.perceive` tries when the paper's
stages give no verified pose, as ONE ordered list of small strategies (:data:`RECOVERY`).

Each strategy is a function of the perceiver, the frame (:class:`~vgpnav_env.perception.pipeline.
Frame`) and the current outcome that returns a better outcome, or None when it does not apply or
finds nothing. Strategies of :attr:`Phase.POSE` act on stages 1-3's outcome (references, backbone
output, motion averaging) before scale recovery and verification; those of :attr:`Phase.RESULT`
on the verified -- or lost -- frame. Every pose a strategy proposes is verified by the images
(:func:`~vgpnav_env.perception.verify.assess`). The geometry they use is here too:
:func:`second_round_references`, :func:`single_pair_fallback`, :func:`slide_on_ray`.
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
    plausible_scale,
    prior_pairs,
    prior_poses,
    prior_support_floor,
    reference_support,
    refine_pose,
)

if TYPE_CHECKING:
    from vgpnav_env.perception.backbones.base import Privileged
    from vgpnav_env.perception.pipeline import Clock, Localization, MetricPose, Perceiver, PerceptionResult


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


def slide_on_ray(
    T_wq: NDArray[np.float64], pairs: Pairs, weights: NDArray[np.float64]
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
    T_wi, out, config = pairs.T_wi, pairs.out, pairs.config
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
    error_px = config.max_epipolar_error_px

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
    if best < max(support(T_wq) * (1.0 + config.ray_slide_gain), config.min_support_matches):
        return None
    before = float(np.linalg.norm(T_wq[:3, 3] - centre))
    return at(best_d), best_d / before


def single_pair_fallback(pairs: Pairs, averaging: MotionAveragingConfig) -> MotionResult | None:
    """The pose of the most confident of the query's ``pairs`` alone (a ``single reference`` motion
    result at backbone scale, to be placed with the ground scale), or None when no pair reaches
    ``single_fallback_confidence`` (or the fallback is off)."""
    out, thr = pairs.out, pairs.config.single_fallback_confidence
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
            refs, out, motion, loc.similarity, perceiver.database.poses, cfg.verify,
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
        motion = single_pair_fallback(perceiver.pairs(loc.references, loc.backbone), cfg.averaging)
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
        moved = slide_on_ray(pose.T_wc, pairs, loc.motion.weights)
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
    hypotheses = prior_poses(pairs, prior, camera_z)
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
        # the wider the prior (prior_support_floor; a prior 1 m off placed a pose 0.76 m off with
        # two references of 31 and 37 matches). The verdict inside the prior has already waived
        # rivals outside it, the share and a wall's plane (its aliases lie elsewhere).
        if verdict.strength < prior_support_floor(prior, v):
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
