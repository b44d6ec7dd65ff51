"""The verdict on one pose: its :class:`Evidence` (support, rivals, plane, mount as size-free
shares) and whether the images confirm it (:func:`verify_pose`), once per pose by :func:`assess`.

With ``VerifyConfig.decision == "rules"`` the verdict is the cascade of checks of
:data:`~vgpnav_env.perception.verify.reasons.VERIFY_CHECKS`; with ``"model"`` the calibrated
:class:`~vgpnav_env.perception.verify.model.VerificationModel` decides from the evidence (the mount
stays a rule: a ground robot's camera cannot leave it).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from vgpnav_env.geometry import camera_yaw_pitch
from vgpnav_env.perception.backbones.base import BackboneOutput
from vgpnav_env.perception.motion_averaging import MotionAveragingConfig
from vgpnav_env.perception.verify.config import PoseGate, VerifyConfig
from vgpnav_env.perception.verify.model import VerificationModel, default_model
from vgpnav_env.perception.verify.reasons import VerifyCheck
from vgpnav_env.perception.verify.rivals import distinct, rival_pairs, rival_poses
from vgpnav_env.perception.verify.support import (
    Pairs,
    explained_confidence,
    off_plane_matches,
    reference_support,
)


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
    ``roll_deg`` / ``height_off_m``: the mount (:attr:`abs_roll_deg` its roll either way);
    ``placed``: inside a state estimate's prior (0 / 1).
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

    @property
    def abs_roll_deg(self) -> float:
        """How far the camera is rolled off level, either way (degrees)."""
        return abs(self.roll_deg)

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
    are those of the rivals inside it. ``evidence``: the size-free quantities of the pose
    (:class:`Evidence`); ``probability``: the calibrated model's probability that the pose is right
    (within 5 cm / 5 deg; nan without a model); ``calibrated``: the model decided ``ok``.
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
    probability: float = float("nan")
    calibrated: bool = False

    @property
    def n_supporting(self) -> int:
        return int(np.count_nonzero(self.support))

    @property
    def confidence(self) -> float:
        """How much to trust an accepted pose (0 when rejected): the calibrated model's probability
        when it decided (``calibrated``), else ``score``."""
        if not self.ok:
            return 0.0
        return self.probability if self.calibrated else self.score

    @property
    def trust(self) -> float:
        """The candidate pose's probability of being right when a model is loaded, else its
        ``score`` (accepted or not): what a confidence ROC ranks poses by."""
        return self.probability if np.isfinite(self.probability) else self.score


def verify_pose(
    T_wq: NDArray[np.float64],
    pairs: Pairs,
    *,
    rivals: Sequence[NDArray[np.float64]] = (),
    camera_z: float = float("nan"),
    prior: PoseGate | None = None,
    model: VerificationModel | None = None,
) -> Verdict:
    """Check the pose ``T_wq`` (metric, W) against the query's ``pairs`` (the references' poses
    ``T_wi`` and the backbone output of the query with exactly these references).

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
    out, config = pairs.out, pairs.config
    raw = reference_support(T_wq, pairs)
    support = np.where(raw >= config.min_support_matches, raw, 0)
    strength = int(support.sum())
    explained = support > 0
    flat = None
    if config.plane_threshold_px:
        flat = replace(pairs, out=off_plane_matches(out, config.plane_threshold_px))

    def off_plane(T: NDArray[np.float64], among: NDArray[np.bool_]) -> int:
        """The most matches off its dominant plane that one reference of ``among`` gives ``T``."""
        if flat is None or not among.any():
            return config.min_off_plane_matches if flat is None else 0
        return int(reference_support(T, flat)[among].max())

    rival_strength, rival = 0, None  # the strongest distinct rival
    # A rival whose best pair is about as confident as the pose's best pair (rival_confidence_ratio).
    ratio, confident = config.rival_confidence_ratio, None
    if ratio is not None and explained.any():
        confident = ratio * float(out.confidence[explained].max())
    confident_strength, confident_rival = 0, None
    inside_strength, inside = 0, None  # the strongest inside the prior (a placed pose's rival)
    claim = config.rival_claim_ratio
    placed = prior is not None and prior.admits(T_wq) and abs(roll_deg(T_wq)) <= config.prior_max_roll_deg
    for T in rivals:
        if implausible_mount(T, camera_z, config):
            continue
        if not distinct(T, T_wq, config):
            continue
        theirs = reference_support(T, pairs)
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
    evidence = Evidence.of(
        raw,
        pairs.own,
        out,
        off_plane=off_plane(T_wq, explained) if flat is not None else 0,
        rival_strength=inside_strength if placed else rival_strength,
        rival_confidence=confident_strength > 0,
        roll_deg=roll_deg(T_wq),
        height_off_m=float(T_wq[2, 3] - camera_z),
        placed=placed,
        ambiguity_references=config.ambiguity_references,
        min_support=config.min_support_matches,
    )

    probability = model.probability(evidence) if model is not None else float("nan")

    def verdict(check: str, detail: str, by_prior: bool = False) -> Verdict:
        reason = VerifyCheck(check).reason if check else ""
        strongest, its = (inside_strength, inside) if placed else (rival_strength, rival)
        score = strength / (strength + strongest + config.confidence_matches)
        return Verdict(
            not reason, reason, detail, score, support, strength, strongest, its, check, by_prior, evidence,
            probability, config.decision == "model",
        )  # fmt: skip

    mount = implausible_mount(T_wq, camera_z, config)
    if mount:
        return verdict(VerifyCheck.MOUNT, mount)
    if config.decision == "model":
        return verdict(*_model_check(evidence, probability, config))

    def alone() -> tuple[str, str]:
        """The check the images alone fail (all rivals count, nothing waived; "" when none) and why."""
        if not _enough_references(support[explained], config):
            return VerifyCheck.SUPPORT, f"{n} reference(s) support the pose (support {raw.tolist()})"
        if config.min_total_support is not None and strength < config.min_total_support:
            return VerifyCheck.SUPPORT, f"{n} references explain only {strength} matches"
        structure = off_plane(T_wq, explained)
        if structure < config.min_off_plane_matches:
            return (
                VerifyCheck.PLANE,
                f"support only on the pairs' dominant planes ({structure} matches off them)",
            )
        if rival_strength >= config.ambiguity_ratio * _strongest(support, config.ambiguity_references):
            distance = np.linalg.norm(rival[:3, 3] - T_wq[:3, 3])
            detail = f"a pose {distance:.1f} m away has support {rival_strength} against {strength}"
            return VerifyCheck.AMBIGUITY, detail
        if confident_rival is not None:
            distance = np.linalg.norm(confident_rival[:3, 3] - T_wq[:3, 3])
            detail = f"a pose {distance:.1f} m away has a pair as confident as the pose's best"
            return VerifyCheck.AMBIGUITY, detail
        if config.min_explained_confidence is not None:
            share = explained_confidence(T_wq, pairs, raw)
            if share < config.min_explained_confidence:
                return VerifyCheck.SHARE, f"the pose explains {share:.0%} of the pairs' confidence"
        return "", f"{n} references, support {strength}, rival {rival_strength}"

    if not placed:
        return verdict(*alone())
    inside_prior = _placed_verdict(verdict, support, inside, inside_strength, T_wq, config)
    return replace(inside_prior, by_prior=bool(alone()[0])) if inside_prior.ok else inside_prior


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
            VerifyCheck.SUPPORT,
            f"{n} reference(s) support the pose inside the prior (support {support.tolist()})",
        )
    if rival is not None and rival_strength >= config.ambiguity_ratio * _strongest(
        support, config.ambiguity_references
    ):
        distance = np.linalg.norm(rival[:3, 3] - T_wq[:3, 3])
        detail = f"a pose {distance:.1f} m away inside the prior has support {rival_strength}"
        return verdict(VerifyCheck.AMBIGUITY, detail)
    n, strength = np.count_nonzero(support), int(support.sum())
    return verdict("", f"inside the prior: {n} references, support {strength}")


def roll_deg(T_wc: NDArray[np.float64]) -> float:
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
    roll = roll_deg(T_wc)
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


def _model_check(evidence: Evidence, probability: float, config: VerifyConfig) -> tuple[str, str]:
    """The calibrated decision: accept at ``accept_probability`` or above; below it the frame is
    ambiguous when a distinct rival has at least ``ambiguity_ratio`` of the pose's support, else
    unverified."""
    if not np.isfinite(probability):
        return VerifyCheck.MODEL, "no calibrated model is installed"
    if probability >= config.accept_probability:
        return "", f"probability {probability:.2f} that the pose is right"
    r = config.ambiguity_ratio
    if evidence.rival_margin <= (1 - r) / (1 + r):
        return VerifyCheck.AMBIGUITY, f"probability {probability:.2f}; a rival has comparable support"
    return VerifyCheck.MODEL, f"probability {probability:.2f} that the pose is right"


@dataclass(frozen=True)
class Assessment:
    """:func:`assess`'s answer: the ``verdict`` on the pose and the ``rivals`` it was weighed
    against, for a caller that weighs another pose of these pairs."""

    verdict: Verdict
    rivals: list[NDArray[np.float64]]


def assess(
    T_wq: NDArray[np.float64],
    pairs: Pairs,
    *,
    scale: float,
    averaging: MotionAveragingConfig,
    camera_z: float = float("nan"),
    prior: PoseGate | None = None,
    rivals: Sequence[NDArray[np.float64]] = (),
) -> Assessment:
    """The chain support -> rivals -> verdict of one pose ``T_wq`` (metric, W) against the query's
    ``pairs``: the pairs it does not explain, or in small part (:func:`rival_pairs`), give its
    rival poses (:func:`rival_poses`, placed at ``scale`` metres per backbone unit), appended to
    ``rivals``; :func:`verify_pose` weighs it against them, with the installed calibrated model
    (:func:`~vgpnav_env.perception.verify.model.default_model`)."""
    support = rival_pairs(reference_support(T_wq, pairs), pairs)
    theirs = [*rivals, *rival_poses(T_wq, pairs, support, scale, averaging)]
    verdict = verify_pose(T_wq, pairs, rivals=theirs, camera_z=camera_z, prior=prior, model=default_model())
    return Assessment(verdict, theirs)
