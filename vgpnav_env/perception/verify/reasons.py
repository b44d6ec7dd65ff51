"""Why a frame is lost and which verification check rejected its pose, as str-valued enums (records
and JSON keep the plain strings)."""

from __future__ import annotations

from enum import StrEnum


class LostReason(StrEnum):
    """Why a frame is lost (:attr:`~vgpnav_env.perception.pipeline.PerceptionResult.reason`)."""

    TOO_FEW_MATCHES = "too few matches"
    NO_CONSENSUS = "no consensus"
    NO_GROUND = "no ground"
    INCONSISTENT_MOTION = "inconsistent motion"
    UNVERIFIED = "unverified"
    AMBIGUOUS = "ambiguous"


#: Lost reason -> what it means (reports define their labels from it).
LOST_REASONS: dict[LostReason, str] = {
    LostReason.TOO_FEW_MATCHES: "no reference pair passed the backbone (too few consistent feature matches)",
    LostReason.NO_CONSENSUS: "the references' poses disagree (rotation consensus, ray triangulation, camera "
    "height)",
    LostReason.NO_GROUND: "no metric scale: no ground plane and no ray-implied scale",
    LostReason.INCONSISTENT_MOTION: "the pose lies outside the caller's odometry gate (PoseGate), or, "
    "verified, outside the prior of its state estimate",
    LostReason.UNVERIFIED: "the images do not confirm the pose (verify_pose: epipolar support, gravity, "
    "height)",
    LostReason.AMBIGUOUS: "the images confirm a distinct rival pose as well (e.g. identical rooms)",
}


class VerifyCheck(StrEnum):
    """The check of :func:`~vgpnav_env.perception.verify.verify_pose` that rejected a pose, in the
    order they run (:attr:`~vgpnav_env.perception.verify.Verdict.check`)."""

    MOUNT = "mount"
    SUPPORT = "support"
    PLANE = "plane"
    AMBIGUITY = "ambiguity"
    SHARE = "share"
    MODEL = "model"

    @property
    def reason(self) -> LostReason:
        """The lost reason of a pose this check rejects."""
        return LostReason.AMBIGUOUS if self is VerifyCheck.AMBIGUITY else LostReason.UNVERIFIED


#: Check -> what rejects a pose ("ambiguity" gives the lost reason "ambiguous", the others "unverified").
VERIFY_CHECKS: dict[VerifyCheck, str] = {
    VerifyCheck.MOUNT: "the camera's roll, pitch or height is not the robot mount's",
    VerifyCheck.SUPPORT: "too few references, or too few matches, explain the pose (epipolar support)",
    VerifyCheck.PLANE: "the pose explains matches only on the pairs' dominant planes",
    VerifyCheck.AMBIGUITY: "a distinct rival pose has comparable support",
    VerifyCheck.SHARE: "the pose explains too small a share of the pairs' confidence",
    VerifyCheck.MODEL: "the calibrated model gives the pose too low a probability of being right",
}
