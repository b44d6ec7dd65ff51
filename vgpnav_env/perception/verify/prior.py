"""The prior's view of a frame: the rival of a pose that a state estimate's prior (:class:`PoseGate`,
e.g. the EKF's) picks when the images alone do not place the frame, confirmed by the images
(:func:`assess`), and the pairs that agree with the prior."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from vgpnav_env.geometry import camera_yaw_pitch, make_pose, wrap_angle
from vgpnav_env.perception.backbones.base import BackboneOutput
from vgpnav_env.perception.motion_averaging import MotionAveragingConfig
from vgpnav_env.perception.verify.config import PoseGate
from vgpnav_env.perception.verify.support import Pairs
from vgpnav_env.perception.verify.verdict import Verdict, assess


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
