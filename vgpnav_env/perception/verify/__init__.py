"""Is this pose true? Verification of a frame's pose by the images, around one :class:`Evidence`
value per pose.

- :mod:`.support`: the query's :class:`Pairs` and how many of its matches with each reference a
  pose explains;
- :mod:`.rivals`: the other places the pairs point to;
- :mod:`.verdict`: the chain support -> rivals -> :class:`Verdict` (:func:`assess`), once;
- :mod:`.model`: the calibrated model, evidence -> probability that the pose is right;
- :mod:`.prior`: the rival a state estimate's prior picks, and the pairs that agree with it;
- :mod:`.scale_checks`: the camera height and scale checks before verification;
- :mod:`.reasons`: lost reasons and check names (str-valued enums).

Settings: :class:`VerifyConfig` (``PerceptionConfig.verify``). Poses are ``T_wc`` / ``T_wq``
(OpenCV camera -> world, metres); backbone translations are in the backbone's unknown units until
a scale (metres per unit) is applied.
"""

from vgpnav_env.perception.verify.config import PoseGate, VerifyConfig
from vgpnav_env.perception.verify.model import VerificationModel, default_model, fit_model
from vgpnav_env.perception.verify.prior import prior_hypothesis, prior_pairs
from vgpnav_env.perception.verify.reasons import LOST_REASONS, VERIFY_CHECKS, LostReason, VerifyCheck
from vgpnav_env.perception.verify.rivals import distinct, rival_pairs, rival_poses
from vgpnav_env.perception.verify.scale_checks import check_height, check_scale, plausible_scale
from vgpnav_env.perception.verify.support import (
    Pairs,
    epipolar_support,
    explained_confidence,
    off_plane_matches,
    pair_support,
    reference_support,
    refine_pose,
)
from vgpnav_env.perception.verify.verdict import (
    Assessment,
    Evidence,
    Verdict,
    assess,
    implausible_mount,
    verify_pose,
)

__all__ = [
    "LOST_REASONS",
    "VERIFY_CHECKS",
    "Assessment",
    "Evidence",
    "LostReason",
    "Pairs",
    "PoseGate",
    "VerificationModel",
    "Verdict",
    "VerifyCheck",
    "VerifyConfig",
    "assess",
    "check_height",
    "check_scale",
    "default_model",
    "distinct",
    "epipolar_support",
    "explained_confidence",
    "fit_model",
    "implausible_mount",
    "off_plane_matches",
    "pair_support",
    "plausible_scale",
    "prior_hypothesis",
    "prior_pairs",
    "reference_support",
    "refine_pose",
    "rival_pairs",
    "rival_poses",
    "verify_pose",
]
