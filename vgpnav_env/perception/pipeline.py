"""VGP-Nav perception: one RGB image + the database -> metric pose and metric obstacle map.

Per frame (paper Sec. III, DESIGN.md "Perception"):

1. retrieval: VLAD similarity to every database image, then :func:`select_references`
   (geometry-aware Alg. 1, or plain top-k);
2. backbone: query first, then the references (database indices as feature-cache keys);
   relative poses ``T_qi`` and query depth at one unknown scale;
3. motion averaging: metric ``T_wc`` from the references' known poses; when fewer than
   ``expand_below_inliers`` references agree, a second round runs steps 2-3 on database images
   chosen around the first round's pose hypotheses (the best round is kept);
4. ground-anchored scale: the ground peak of the reconstruction's heights in the gravity frame
   (searched near the height the ray-implied scale of step 3 predicts), scaled to the camera
   height above the ground anchored at initialisation (robot standing still, known
   camera-to-base height); falls back to the ray-implied scale when no ground is seen;
5. occupancy: metric points (confident pixels, every ``point_stride``-th pixel) classified by
   height and fused into the perceiver's log-odds map on top of the database's prior.

A frame whose pose cannot be estimated gives ``status="lost"`` with a ``reason`` from
:data:`LOST_REASONS` -- never an exception (bad arguments still raise ``ValueError``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from vgpnav_env.geometry import PinholeCamera, camera_yaw_pitch, make_pose, rotation_angle, wrap_angle
from vgpnav_env.perception.backbones import make_backbone
from vgpnav_env.perception.backbones.base import Backbone, BackboneOutput, Privileged
from vgpnav_env.perception.database import Database
from vgpnav_env.perception.motion_averaging import MotionAveragingConfig, MotionResult, average_motion
from vgpnav_env.perception.occupancy import OccupancyConfig, PointClasses
from vgpnav_env.perception.points import depth_points
from vgpnav_env.perception.retrieval import RetrievalConfig, pose_guided_references, select_references
from vgpnav_env.perception.scale_recovery import (
    GroundAnchor,
    GroundEstimate,
    ScaleConfig,
    ScaleEstimate,
    ground_peak,
    reconstruction_points,
    recover_metric_points,
)
from vgpnav_env.robot import CAMERA_HEIGHT

logger = logging.getLogger(__name__)

#: Why a frame is lost: no reference pair passed the backbone; the references' poses disagree
#: (rotation consensus, ray triangulation); no metric scale (no ground and no ray scale); the pose
#: lies outside the caller's :class:`PoseGate` (e.g. odometry since the last fix).
LOST_REASONS = ("too few matches", "no consensus", "no ground", "inconsistent motion")
TIMING_KEYS = ("retrieval", "backbone", "motion_averaging", "scale_recovery", "occupancy", "total")


@dataclass(frozen=True)
class PerceptionConfig:
    """All pipeline settings; the ablation switches are ``retrieval.method`` (geometry | topk),
    ``averaging.method`` (weighted | single) and ``scale.enabled``.

    ``camera_height``: the calibrated camera-to-base height (metres), the metric anchor.
    ``scale_check_ratio``: when the ground scale and the ray-implied scale of motion averaging
    differ by more than this factor, the ground peak is taken to be something else (a table
    top, a plant pot seen from above) and the ray-implied scale is used (None: never). The
    ground is first searched within ``ScaleConfig.prior_tolerance`` of the ray-implied height
    (such a peak always passes the check); only when nothing is there does the dominant peak
    compete, and the check decides (on ``home`` this fixed a 25 % ray-scale error and kept a
    table top at 2.2x out).
    ``single_fallback_confidence``: when weighted motion averaging fails (fewer than two
    consistent rays) but one pair's backbone confidence is at least this, the pose comes from
    that pair alone, placed with the ground scale at the calibrated camera height (as the
    ``single`` ablation does); None = such frames are lost. Requires scale recovery. Measured
    on ``home`` (classical, 50 queries, lost / recall@5cm): None 29 / 0.36, 0.5 26 / 0.40,
    0.3 23 / 0.46, 0.15 21 / 0.50, with the same 2 gross (> 0.25 m) errors throughout.
    ``expand_below_inliers``: when motion averaging keeps fewer consistent references than
    this (a failed pose counts 0), a second round verifies references chosen by pose: up to
    ``expand_hypotheses`` distinct pose hypotheses (the averaged pose, the most confident pairs'
    ``R_wi R_iq`` at their reference centres) select database cameras within ``expand_radius``
    metres and ``expand_max_angle_deg`` of them; the round with more consistent references wins
    (None = one round, the paper's pipeline). Retrieval by appearance alone often leaves a
    single overlapping reference in a large database; the second round finds its neighbours.
    ``pose_height_tolerance``: a pose whose camera height above the anchored ground differs
    from ``camera_height`` by more than this (metres) is rejected like a failed consensus
    (a ground robot's camera stays at its height; None = never).
    """

    retrieval: RetrievalConfig = field(default_factory=RetrievalConfig)
    averaging: MotionAveragingConfig = field(default_factory=MotionAveragingConfig)
    scale: ScaleConfig = field(default_factory=ScaleConfig)
    occupancy: OccupancyConfig = field(default_factory=OccupancyConfig)
    camera_height: float = CAMERA_HEIGHT
    scale_check_ratio: float | None = 1.5
    single_fallback_confidence: float | None = 0.15
    expand_below_inliers: int | None = 3
    expand_hypotheses: int = 2
    expand_radius: float = 1.5
    expand_max_angle_deg: float = 35.0
    pose_height_tolerance: float | None = 0.3

    def __post_init__(self) -> None:
        if not self.camera_height > 0:
            raise ValueError(f"camera_height must be positive metres, got {self.camera_height}")
        if self.scale_check_ratio is not None and self.scale_check_ratio <= 1:
            raise ValueError(f"scale_check_ratio must be > 1 or None, got {self.scale_check_ratio}")

    @classmethod
    def ablation(
        cls,
        *,
        retrieval: str = "geometry",
        averaging: str = "weighted",
        scale: bool = True,
        k: int = 10,
        camera_height: float = CAMERA_HEIGHT,
    ) -> PerceptionConfig:
        """The default config with the three ablation switches set (and ``k`` references)."""
        return cls(
            retrieval=RetrievalConfig(k=k, method=retrieval),
            averaging=MotionAveragingConfig(method=averaging),
            scale=ScaleConfig(enabled=scale),
            camera_height=camera_height,
        )


@dataclass(frozen=True)
class PoseGate:
    """Where the caller expects the camera (e.g. its last fix moved by odometry): a pose whose
    horizontal position is more than ``max_distance`` metres from ``T_wc``'s, or whose heading
    (camera yaw) differs by more than ``max_yaw`` radians, is lost ("inconsistent motion") and
    is not fused into the map. One wrong reference set can place a frame metres away; a robot
    cannot jump there in one step.
    """

    T_wc: NDArray[np.float64]
    max_distance: float
    max_yaw: float

    def __post_init__(self) -> None:
        if np.shape(self.T_wc) != (4, 4):
            raise ValueError(f"PoseGate.T_wc must be a 4x4 pose, got shape {np.shape(self.T_wc)}")
        if not (self.max_distance > 0 and self.max_yaw > 0):
            raise ValueError(
                f"max_distance (m) and max_yaw (rad) must be positive, "
                f"got {self.max_distance}, {self.max_yaw}"
            )

    def deviation(self, T_wc: NDArray[np.float64]) -> tuple[float, float]:
        """(horizontal distance m, absolute heading difference rad) of ``T_wc`` from the gate's pose."""
        distance = float(np.linalg.norm(T_wc[:2, 3] - self.T_wc[:2, 3]))
        yaw = abs(float(wrap_angle(camera_yaw_pitch(T_wc)[0] - camera_yaw_pitch(self.T_wc)[0])))
        return distance, yaw

    def admits(self, T_wc: NDArray[np.float64]) -> bool:
        distance, yaw = self.deviation(T_wc)
        return distance <= self.max_distance and yaw <= self.max_yaw


@dataclass(frozen=True)
class PerceptionResult:
    """One frame's navigation-ready state (immutable; the fused map is :attr:`Perceiver.map`).

    ``T_wc``: metric camera pose (4x4, OpenCV camera -> world); None when lost.
    ``points_w`` (N, 3) float32 metric world points of the query (confident, subsampled
    pixels; empty when lost) and their ``classes`` (free ground / obstacle masks).
    ``references``: database indices used, best match first. ``scale``: metres per backbone
    unit (nan when lost) and ``scale_source`` (ground | fallback | disabled | none).
    ``z_ground``: anchored floor height (W, metres). ``timings``: wall seconds per stage
    (:data:`TIMING_KEYS`) and ``cpu``: the process's CPU seconds for the whole call (all
    threads; less sensitive than wall time to other processes sharing the cores).
    """

    status: str
    reason: str
    T_wc: NDArray[np.float64] | None
    points_w: NDArray[np.float32]
    classes: PointClasses | None
    references: NDArray[np.int64]
    scale: float
    scale_source: str
    z_ground: float
    timings: dict[str, float]
    motion: MotionResult | None = None
    ground: GroundEstimate | None = None
    backbone: BackboneOutput | None = None
    n_confident_pairs: int = 0
    detail: str = ""

    @property
    def localized(self) -> bool:
        return self.status == "localized"


def _lost(reason: str, detail: str, refs: NDArray[np.int64], **kw) -> PerceptionResult:
    return PerceptionResult(
        status="lost",
        reason=reason,
        T_wc=kw.pop("T_wc", None),
        points_w=np.zeros((0, 3), np.float32),
        classes=None,
        references=refs,
        scale=float("nan"),
        scale_source="none",
        z_ground=kw.pop("z_ground", float("nan")),
        timings=kw.pop("timings"),
        detail=detail,
        **kw,
    )


class Perceiver:
    """Stateful VGP-Nav perception for one robot episode.

    ``backbone``: a :class:`Backbone` or a registry name (built with
    :func:`~vgpnav_env.perception.backbones.make_backbone` for ``database``). ``camera`` defaults
    to the database camera (query images must have its size). :attr:`map` is the fused log-odds
    map of the episode (the live object). Call :meth:`reset` per episode, optionally
    :meth:`initialize` with frames taken standing still (else the first localized frame anchors
    the ground), then :meth:`perceive` per frame.
    ``privileged`` (simulated backbone only) carries the query's true ``T_wq`` and depth; the
    references' ``T_wi`` are filled in here from the database.
    """

    def __init__(
        self,
        database: Database,
        backbone: Backbone | str = "classical",
        camera: PinholeCamera | None = None,
        config: PerceptionConfig | None = None,
    ) -> None:
        self.database = database
        self.backbone = make_backbone(backbone, database=database) if isinstance(backbone, str) else backbone
        self.camera = camera or database.camera
        if (self.camera.width, self.camera.height) != (database.camera.width, database.camera.height):
            raise ValueError(
                f"query camera {self.camera.width}x{self.camera.height} differs from the database camera "
                f"{database.camera.width}x{database.camera.height}; build both at the same size"
            )
        self.config = config or PerceptionConfig()
        self.reset()

    def reset(self) -> None:
        """Forget the episode: a fresh map from the prior and no ground anchor."""
        self.map = self.database.new_map(self.config.occupancy)
        self.anchor = GroundAnchor(self.config.scale)

    @property
    def initialized(self) -> bool:
        return self.anchor.initialized

    def initialize(
        self,
        images: Sequence[NDArray[np.uint8]] | NDArray[np.uint8],
        privileged: Sequence[Privileged | None] | Privileged | None = None,
    ) -> list[PerceptionResult]:
        """Anchor the ground from frames taken while the robot stands still (paper "Ground Height
        Initialization"): ``z_ground = mean(t_wc.z) - camera_height`` over the localized frames.
        Then every frame is perceived (and fused) with the anchor. If none localizes, the
        anchor stays unset and the next localized :meth:`perceive` call sets it.
        """
        if isinstance(images, np.ndarray) and images.ndim == 3:
            images = [images]
        priv = privileged if isinstance(privileged, Sequence) else [privileged] * len(images)
        if len(priv) != len(images):
            raise ValueError(f"got {len(priv)} privileged entries for {len(images)} images")
        observations = []
        for rgb, p in zip(images, priv, strict=True):
            loc = self._localize(rgb, p)
            if loc.motion is not None and loc.motion.ok:
                observations.append((loc.motion.T_wq, None))
        if observations:
            self.anchor.initialize(observations, self.config.camera_height)
        return [self.perceive(rgb, p) for rgb, p in zip(images, priv, strict=True)]

    def perceive(
        self, rgb: NDArray[np.uint8], privileged: Privileged | None = None, gate: PoseGate | None = None
    ) -> PerceptionResult:
        """Perceive one RGB frame (uint8 HxWx3 of the camera's size) and fuse it into :attr:`map`.

        With a ``gate``, a pose outside it is lost ("inconsistent motion"), nothing is fused.
        """
        t_start, cpu_start = time.perf_counter(), time.process_time()
        loc = self._localize(rgb, privileged)
        timings = loc.timings
        if loc.status == "lost":
            fallback = self._single_fallback(loc)
            if fallback is None:
                timings["total"] = time.perf_counter() - t_start
                timings["cpu"] = time.process_time() - cpu_start
                return loc
            loc = fallback
        motion, out = loc.motion, loc.backbone
        t0 = time.perf_counter()
        T_wc = motion.T_wq

        def lost(reason: str, detail: str, **kw) -> PerceptionResult:
            """This frame lost after motion averaging (its pose kept for inspection), nothing fused."""
            timings["scale_recovery"] += time.perf_counter() - t0
            timings["total"] = time.perf_counter() - t_start
            timings["cpu"] = time.process_time() - cpu_start
            return _lost(
                reason,
                detail,
                loc.references,
                T_wc=T_wc,
                timings=timings,
                motion=motion,
                backbone=out,
                n_confident_pairs=loc.n_confident_pairs,
                **kw,
            )

        single = motion.reason == "single reference" and self.config.scale.enabled
        if single:
            # One reference's translation is only known at the backbone scale: place the camera
            # with the ground scale at the calibrated camera height (the single-view baseline).
            ground = self._ground(out, T_wc, None)
            if ground.found:
                est = ScaleEstimate(self.config.camera_height / -ground.height_b, "ground")
                T_wc = self._single_pose(T_wc, loc.references, motion, out, est.scale)
            else:
                est = ScaleEstimate(float("nan"), "none")
        if gate is not None and not gate.admits(T_wc):
            distance, yaw = gate.deviation(T_wc)
            return lost(
                "inconsistent motion",
                f"pose {distance:.2f} m / {np.degrees(yaw):.0f} deg from the expected one "
                f"(gate {gate.max_distance:.2f} m / {np.degrees(gate.max_yaw):.0f} deg)",
            )
        if not self.anchor.initialized and not (single and not est.ok):
            self.anchor.initialize([(T_wc, None)], self.config.camera_height)
        if not single:
            prior = None
            if self.anchor.initialized and self.config.scale.enabled:
                prior = self.anchor.expected_height_b(T_wc, motion.scale_from_rays)
            ground = self._ground(out, T_wc, prior)
            if prior is not None and not ground.found:
                # Nothing near the ray-implied height: the rays' scale may be off (a weak pair);
                # the dominant ground peak counts if it passes the scale check against them.
                ground = self._ground(out, T_wc, None)
            est = self.anchor.scale_for(T_wc, ground, fallback_scale=motion.scale_from_rays)
            est = self._check_scale(est, motion.scale_from_rays)
        z_ground = float(self.anchor.z_ground) if self.anchor.initialized else float("nan")
        if not est.ok:
            detail = "no ground peak and no ray-implied scale"
            return lost("no ground", detail, z_ground=z_ground, ground=ground)
        occ = self.config.occupancy
        points_q, _ = depth_points(
            self.camera,
            out.query_depth,
            out.query_depth_confidence,
            stride=occ.point_stride,
            min_confidence=occ.min_confidence,
        )
        points_q = points_q[points_q[:, 2] * est.scale <= self.config.occupancy.max_depth]
        points_w = recover_metric_points(points_q, T_wc, est.scale)
        timings["scale_recovery"] += time.perf_counter() - t0

        t0 = time.perf_counter()
        classes = self.map.update(
            points_w,
            z_ground,
            self.config.camera_height,
            camera_xy=T_wc[:2, 3],
            free_tol=occ.free_tol,
            obstacle_min=occ.obstacle_min,
        )
        timings["occupancy"] = time.perf_counter() - t0
        timings["total"] = time.perf_counter() - t_start
        timings["cpu"] = time.process_time() - cpu_start
        return PerceptionResult(
            status="localized",
            reason="",
            T_wc=T_wc,
            points_w=points_w.astype(np.float32),
            classes=classes,
            references=loc.references,
            scale=est.scale,
            scale_source=est.source,
            z_ground=z_ground,
            timings=timings,
            motion=motion,
            ground=ground,
            backbone=out,
            n_confident_pairs=loc.n_confident_pairs,
            detail=loc.detail,
        )

    def _single_fallback(self, loc: PerceptionResult) -> PerceptionResult | None:
        """``loc`` localized from its most confident pair alone, or None (see PerceptionConfig)."""
        thr = self.config.single_fallback_confidence
        out = loc.backbone
        if thr is None or loc.motion is None or out is None or not self.config.scale.enabled:
            return None
        if float(out.confidence.max()) < thr:
            return None
        t0 = time.perf_counter()
        config = replace(self.config.averaging, method="single", single_reference="confidence")
        motion = average_motion(
            self.database.poses[loc.references], out.T_qi, out.confidence, config, scale_valid=out.scale_valid
        )
        loc.timings["motion_averaging"] += time.perf_counter() - t0
        return replace(
            loc,
            status="localized",
            reason="",
            T_wc=motion.T_wq,
            motion=motion,
            detail=f"single-pair fallback after: {loc.detail}",
        )

    def _check_scale(self, est: ScaleEstimate, ray_scale: float) -> ScaleEstimate:
        r = self.config.scale_check_ratio
        if r is None or est.source != "ground" or not (np.isfinite(ray_scale) and ray_scale > 0):
            return est
        if 1.0 / r <= est.scale / ray_scale <= r:
            return est
        return ScaleEstimate(float(ray_scale), "fallback")

    def _single_pose(
        self,
        T_wq: NDArray[np.float64],
        refs: NDArray[np.int64],
        motion: MotionResult,
        out: BackboneOutput,
        scale: float,
    ) -> NDArray[np.float64]:
        """The single reference's pose with its translation at ``scale`` metres per backbone unit."""
        i = int(np.argmax(motion.weights))
        T_wi = self.database.poses[refs[i]]
        T = T_wq.copy()
        T[:3, 3] = _centre_along_pair(T_wi, out.T_iq[i], scale)
        return T

    def _ground(
        self, out: BackboneOutput, T_wc: NDArray[np.float64], prior_height_b: float | None
    ) -> GroundEstimate:
        """Ground peak (backbone units) of the whole reconstruction: confident query pixels plus the
        reference depths a backbone returns (moved into the query frame, weighted by pair confidence
        on the common scale). ``prior_height_b`` restricts the peak to near the expected height."""
        weights = out.confidence * out.scale_valid if out.reference_depths is not None else None
        points, w = reconstruction_points(
            self.camera,
            out.query_depth,
            out.query_depth_confidence,
            out.T_qi,
            out.reference_depths,
            weights,
            stride=self.config.occupancy.point_stride,
            min_confidence=self.config.occupancy.min_confidence,
        )
        return ground_peak(points, T_wc[:3, :3], w, self.config.scale, prior_height_b=prior_height_b)

    def _localize(self, rgb: NDArray[np.uint8], privileged: Privileged | None) -> PerceptionResult:
        """Stages 1-3 (retrieval, backbone, motion averaging): a lost result or one with motion set.

        When the first round leaves fewer than ``expand_below_inliers`` consistent references, a
        second round verifies references chosen around its pose hypotheses (see
        :class:`PerceptionConfig`) and the better round is kept.
        """
        rgb = np.asarray(rgb)
        expected = (self.camera.height, self.camera.width, 3)
        if rgb.shape != expected or rgb.dtype != np.uint8:
            raise ValueError(f"query image must be uint8 with shape {expected}, got {rgb.dtype} {rgb.shape}")
        db = self.database
        timings = dict.fromkeys(TIMING_KEYS, 0.0)
        t0 = time.perf_counter()
        sims = db.index.similarity(rgb)
        if not np.all(np.isfinite(sims)):
            sims = np.nan_to_num(sims, nan=-1.0, posinf=-1.0, neginf=-1.0)
        refs = select_references(sims, db.poses, self.config.retrieval)
        timings["retrieval"] = time.perf_counter() - t0
        if len(refs) == 0:
            return _lost("too few matches", "empty database", refs, timings=timings)

        out, motion = self._round(rgb, refs, privileged, timings)
        expansion = self._expansion(refs, out, motion, sims)
        if len(expansion):
            out2, motion2 = self._round(rgb, expansion, privileged, timings)
            logger.debug(
                "expansion: round 1 %s ok=%s (%s) conf %s; round 2 %s ok=%s (%s) conf %s",
                refs.tolist(),
                motion.ok,
                motion.reason,
                np.round(out.confidence, 2).tolist(),
                expansion.tolist(),
                motion2.ok,
                motion2.reason,
                np.round(out2.confidence, 2).tolist(),
            )
            if _round_rank(out2, motion2) > _round_rank(out, motion):
                refs, out, motion = expansion, out2, motion2
        n_conf = int((out.confidence > 0).sum())
        if n_conf == 0:
            return _lost(
                "too few matches",
                f"no reference pair passed the backbone (matches {out.n_matches.tolist()})",
                refs,
                timings=timings,
                backbone=out,
            )
        if not motion.ok:
            reason = "too few matches" if motion.reason == "too few references" else "no consensus"
            return _lost(
                reason,
                motion.reason,
                refs,
                timings=timings,
                motion=motion,
                backbone=out,
                n_confident_pairs=n_conf,
            )

        return PerceptionResult(
            status="localized",
            reason="",
            T_wc=motion.T_wq,
            points_w=np.zeros((0, 3), np.float32),
            classes=None,
            references=refs,
            scale=float("nan"),
            scale_source="none",
            z_ground=float("nan"),
            timings=timings,
            motion=motion,
            backbone=out,
            n_confident_pairs=n_conf,
        )

    def _round(
        self,
        rgb: NDArray[np.uint8],
        refs: NDArray[np.int64],
        privileged: Privileged | None,
        timings: dict[str, float],
    ) -> tuple[BackboneOutput, MotionResult]:
        """Backbone + motion averaging over ``refs`` (timings accumulate); a pose whose camera height
        above the anchored ground is off by more than ``pose_height_tolerance`` is not ok."""
        db = self.database
        t0 = time.perf_counter()
        if privileged is not None:
            privileged = replace(privileged, T_wi=db.poses[refs], reference_depths=None)
        out = self.backbone(
            rgb,
            [db.images[i] for i in refs],
            self.camera,
            privileged=privileged,
            reference_keys=[int(i) for i in refs],
        )
        timings["backbone"] += time.perf_counter() - t0
        t0 = time.perf_counter()
        motion = average_motion(
            db.poses[refs], out.T_qi, out.confidence, self.config.averaging, scale_valid=out.scale_valid
        )
        cfg = self.config
        weighted = motion.ok and motion.reason != "single reference"
        tol = cfg.pose_height_tolerance
        if weighted and tol is not None and self.anchor.initialized:
            off = self.anchor.camera_height(motion.T_wq) - cfg.camera_height
            if abs(off) > tol:
                motion.ok, motion.reason = False, f"camera height off by {off:+.2f} m"
        timings["motion_averaging"] += time.perf_counter() - t0
        return out, motion

    def _expansion(
        self, refs: NDArray[np.int64], out: BackboneOutput, motion: MotionResult, sims: NDArray[np.float64]
    ) -> NDArray[np.int64]:
        """References of the second round (empty: none needed or none found).

        Hypotheses: the averaged pose (when ok), then the most confident pairs' poses (rotation
        ``R_wi R_iq``; centre along the pair's ray at the scale its ground peak gives at the
        calibrated camera height, else the reference centre), distinct ones only. Each hypothesis'
        pair is kept (the averaged pose keeps its inliers; up to k / 2 kept), the rest are new
        database images around the hypotheses (:func:`pose_guided_references`). Without any
        hypothesis (no pair passed), the k most similar database images not tried yet.
        """
        cfg = self.config
        below = cfg.expand_below_inliers
        n_inliers = int(motion.inliers.sum()) if motion.ok else 0
        if below is None or n_inliers >= below or cfg.averaging.method != "weighted":
            return np.zeros(0, np.int64)
        poses = self.database.poses
        hypotheses: list[NDArray[np.float64]] = []
        keep: list[int] = []
        if motion.ok:
            hypotheses.append(motion.T_wq)
            keep += [int(i) for i in refs[motion.inliers]]
        consensus = np.deg2rad(cfg.averaging.consensus_deg)
        for j in np.argsort(-out.confidence, kind="stable"):
            if out.confidence[j] <= 0 or len(hypotheses) >= cfg.expand_hypotheses + int(motion.ok):
                break
            T_wi = poses[refs[j]]
            T = make_pose(T_wi[:3, :3] @ out.T_iq[j, :3, :3], T_wi[:3, 3])
            if cfg.scale.enabled:
                # Along the pair's ray, at the ground scale of the calibrated camera height.
                ground = self._ground(out, T, None)
                if ground.found:
                    T[:3, 3] = _centre_along_pair(T_wi, out.T_iq[j], cfg.camera_height / -ground.height_b)
            if any(
                np.linalg.norm(T[:3, 3] - h[:3, 3]) <= cfg.expand_radius
                and rotation_angle(T[:3, :3], h[:3, :3]) <= consensus
                for h in hypotheses
            ):
                continue
            hypotheses.append(T)
            keep.append(int(refs[j]))
        k = cfg.retrieval.k
        if not hypotheses:
            untried = np.argsort(-sims, kind="stable")
            return untried[~np.isin(untried, refs)][:k].astype(np.int64)
        keep = list(dict.fromkeys(keep))[: max(1, k // 2)]
        new = pose_guided_references(
            poses,
            np.array(hypotheses),
            k - len(keep),
            exclude=refs,
            radius=cfg.expand_radius,
            max_angle_deg=cfg.expand_max_angle_deg,
        )
        if len(new) == 0:
            return np.zeros(0, np.int64)
        return np.concatenate([np.array(keep, np.int64), new])


def _centre_along_pair(
    T_wi: NDArray[np.float64], T_iq: NDArray[np.float64], scale: float
) -> NDArray[np.float64]:
    """World camera centre of a query placed by one pair: reference centre plus the pair's
    translation (backbone units) at ``scale`` metres per unit, rotated into W."""
    return T_wi[:3, 3] + scale * T_wi[:3, :3] @ T_iq[:3, 3]


def _round_rank(out: BackboneOutput, motion: MotionResult) -> tuple[bool, int, float]:
    """Order of two rounds' outcomes: a pose, then more consistent references, then the best pair."""
    n_inliers = int(motion.inliers.sum()) if motion.ok else 0
    return motion.ok, n_inliers, float(out.confidence.max(initial=0.0))


def perceive(
    query_rgb: NDArray[np.uint8],
    database: Database,
    *,
    backbone: Backbone | str = "classical",
    config: PerceptionConfig | None = None,
    privileged: Privileged | None = None,
) -> PerceptionResult:
    """One-shot VGP-Nav perception of a single image (DESIGN.md's ``perceive``).

    The frame itself anchors the ground (as if the robot stood still with its camera at
    ``config.camera_height``); the map starts from the database prior. For a sequence use a
    :class:`Perceiver`, which keeps the anchor and the fused map across frames.
    """
    return Perceiver(database, backbone, config=config).perceive(query_rgb, privileged)
