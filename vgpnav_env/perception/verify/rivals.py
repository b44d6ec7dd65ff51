"""Rivals: the other places the query's pairs point to, which a pose's support is weighed against."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from vgpnav_env.geometry import make_pose, rotation_angle
from vgpnav_env.perception.motion_averaging import MotionAveragingConfig, average_motion, pair_centre
from vgpnav_env.perception.verify.config import VerifyConfig
from vgpnav_env.perception.verify.support import Pairs


def distinct(T_a: NDArray[np.float64], T_b: NDArray[np.float64], config: VerifyConfig) -> bool:
    """Whether two camera poses are distinct places: farther apart than ``rival_distance`` metres or
    turned by more than ``rival_angle_deg``."""
    far = np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]) > config.rival_distance
    return bool(far or rotation_angle(T_a[:3, :3], T_b[:3, :3]) > np.deg2rad(config.rival_angle_deg))


def rival_poses(
    T_wq: NDArray[np.float64],
    pairs: Pairs,
    support: NDArray[np.int64],
    scale: float,
    averaging: MotionAveragingConfig,
) -> list[NDArray[np.float64]]:
    """Pose hypotheses that compete with ``T_wq``, from the pairs it does not explain
    (``support`` 0; :func:`rival_pairs` also zeroes the pairs it explains in small part): the
    weighted motion average of those pairs (when it succeeds), then each such pair on its own
    (rotation ``R_wi R_iq``, centre along its ray at ``scale`` metres per backbone unit)."""
    T_wi, out = pairs.T_wi, pairs.out
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


def rival_pairs(support: NDArray[np.int64], pairs: Pairs) -> NDArray[np.int64]:
    """``support`` (k,) of a pose (0 where under ``min_support_matches``), also 0 where the pose
    explains fewer than ``rival_claim_ratio`` of the matches the pair's own relative pose explains
    (:attr:`Pairs.own`): the pairs :func:`rival_poses` makes rivals of."""
    config = pairs.config
    support = np.where(support >= config.min_support_matches, support, 0)
    if config.rival_claim_ratio is None:
        return support
    weak = support < config.rival_claim_ratio * pairs.own
    return np.where(weak, 0, support)
