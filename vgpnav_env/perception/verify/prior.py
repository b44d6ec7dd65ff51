"""Prior hypotheses: poses a state estimate's prior (:class:`PoseGate`, e.g. the EKF's) proposes
for a frame the images alone do not place, each still confirmed by the images (:func:`assess`)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from vgpnav_env.geometry import camera_yaw_pitch, make_pose, rotation_angle, wrap_angle
from vgpnav_env.perception.backbones.base import BackboneOutput
from vgpnav_env.perception.motion_averaging import MotionAveragingConfig
from vgpnav_env.perception.verify.config import PoseGate, VerifyConfig
from vgpnav_env.perception.verify.support import Pairs, reference_support
from vgpnav_env.perception.verify.verdict import Verdict, assess, implausible_mount, roll_deg


def prior_hypothesis(
    T_wq: NDArray[np.float64],
    rivals: Sequence[NDArray[np.float64]],
    pairs: Pairs,
    prior: PoseGate,
    *,
    scale: float,
    averaging: MotionAveragingConfig,
    camera_z: float = float("nan"),
) -> tuple[NDArray[np.float64], Verdict] | None:
    """The pose the ``prior`` picks when the images do not confirm ``T_wq`` inside it: of the
    ``rivals`` of ``T_wq`` (:func:`rival_poses`) inside the prior, the one with the most support
    that :func:`verify_pose` confirms as the pose against the query's ``pairs`` (with the prior,
    against its own rivals and ``T_wq``), and its verdict; None when none is confirmed. In
    identical wards the averaged pose is often the other ward's view and the true place's pairs
    make a rival: inside the prior, it is the robot's. ``scale``: metres per backbone unit of the
    rivals' own rivals."""
    best = None
    for T in rivals:
        if not prior.admits(T):
            continue
        verdict = assess(
            T, pairs, scale=scale, averaging=averaging, camera_z=camera_z, prior=prior, rivals=[T_wq]
        ).verdict
        if verdict.ok and (best is None or verdict.strength > best[1].strength):
            best = T, verdict
    return best


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


def prior_poses(pairs: Pairs, prior: PoseGate, camera_z: float) -> list[NDArray[np.float64]]:
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
    T_wi, out, config = pairs.T_wi, pairs.out, pairs.config
    x, y, yaw = np.asarray(prior.pose, float)
    step = config.prior_grid_m
    n = int(np.ceil(prior.max_distance / step))
    offsets = np.stack(np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1)), -1).reshape(-1, 2) * step
    offsets = offsets[np.linalg.norm(offsets, axis=1) <= prior.max_distance]
    fine = np.stack(np.meshgrid(np.arange(-2, 3), np.arange(-2, 3)), -1).reshape(-1, 2) * (step / 4)

    def best(R: NDArray[np.float64], centre: NDArray[np.float64], grid: NDArray[np.float64]):
        poses = [make_pose(R, np.r_[centre + o, camera_z]) for o in grid]
        poses = [T for T in poses if prior.admits(T)]
        scores = [int(reference_support(T, pairs).sum()) for T in poses]
        return poses[int(np.argmax(scores))] if poses else None

    hypotheses: list[NDArray[np.float64]] = []
    for i in np.argsort(-out.confidence, kind="stable"):
        if out.confidence[i] <= 0 or len(hypotheses) >= config.prior_hypotheses:
            break
        R = T_wi[i, :3, :3] @ out.T_iq[i, :3, :3]
        T = make_pose(R, np.array([x, y, camera_z]))
        if abs(roll_deg(T)) > config.prior_max_roll_deg or implausible_mount(T, camera_z, config):
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
