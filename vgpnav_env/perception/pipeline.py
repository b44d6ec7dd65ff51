"""VGP-Nav perception: one RGB image + the database -> metric pose and metric obstacle map.

:meth:`Perceiver.perceive` runs the paper's stages (Sec. III, DESIGN.md "Perception") in order:

1. retrieval: VLAD similarity to every database image, optionally re-scored for the top-N by
   :func:`geometric_rerank`, then :func:`select_references` (geometry-aware Alg. 1, or plain top-k);
2. backbone: query first, then the references (database indices as feature-cache keys);
   relative poses ``T_qi`` and query depth at one unknown scale;
3. motion averaging: metric ``T_wc`` from the references' known poses;
4. ground-anchored scale: the ground peak of the reconstruction's heights in the gravity frame
   (searched near the height the ray-implied scale of step 3 predicts), scaled to the camera
   height above the ground anchored at initialisation (robot standing still, known
   camera-to-base height); falls back to the ray-implied scale when no ground is seen;
5. occupancy: metric points (confident pixels, every ``point_stride``-th pixel) classified by
   height and fused into the perceiver's log-odds map (:attr:`Perceiver.map`) on top of the
   database's prior. With the classical backbone a localized frame's points come from its depth
   swept again at the final pose against the database's metric poses
   (:mod:`~vgpnav_env.perception.posed_depth`, ``PerceptionConfig.depth``), not from the
   backbone's depth at the two-view poses and the ground scale.

What makes localization robust beyond these stages -- the camera-height and scale checks, the
caller's pose gate, a second round of references around the first round's pose hypotheses, the
single-pair fallback -- lives in :mod:`vgpnav_env.perception.verify` (``PerceptionConfig.verify``).

A frame whose pose cannot be estimated gives ``status="lost"`` with a ``reason`` from
:data:`LOST_REASONS` -- never an exception (bad arguments still raise ``ValueError``).
"""

from __future__ import annotations

import copy
import logging
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from vgpnav_env.geometry import PinholeCamera, camera_yaw_pitch, invert_pose, transform_points
from vgpnav_env.perception.backbones import make_backbone
from vgpnav_env.perception.backbones.base import Backbone, BackboneOutput, Privileged
from vgpnav_env.perception.backbones.classical import ClassicalBackbone, rootsift
from vgpnav_env.perception.database import Database
from vgpnav_env.perception.motion_averaging import (
    MotionAveragingConfig,
    MotionResult,
    average_motion,
    pair_centre,
)
from vgpnav_env.perception.occupancy import OccupancyConfig, PointClasses
from vgpnav_env.perception.points import depth_points
from vgpnav_env.perception.posed_depth import PosedDepthConfig, posed_depth, posed_references
from vgpnav_env.perception.retrieval import (
    RetrievalConfig,
    TrackingConfig,
    geometric_rerank,
    select_references,
    tracked_references,
)
from vgpnav_env.perception.scale_recovery import (
    GroundAnchor,
    GroundEstimate,
    ScaleConfig,
    ScaleEstimate,
    ground_peak,
    reconstruction_points,
    recover_metric_points,
)
from vgpnav_env.perception.verify import (
    PoseGate,
    Verdict,
    VerifyConfig,
    check_height,
    check_scale,
    implausible_mount,
    pair_support,
    plausible_scale,
    pooled_pairs,
    prior_hypothesis,
    prior_pairs,
    prior_poses,
    prior_support_floor,
    reference_support,
    refine_pose,
    rival_pairs,
    rival_poses,
    round_rank,
    second_round_references,
    single_pair_fallback,
    slide_on_ray,
    verify_pose,
)
from vgpnav_env.robot import CAMERA_HEIGHT, camera_T_wc

logger = logging.getLogger(__name__)

#: Why a frame is lost: reason -> what it means (reports define their labels from it).
LOST_REASONS: dict[str, str] = {
    "too few matches": "no reference pair passed the backbone (too few consistent feature matches)",
    "no consensus": "the references' poses disagree (rotation consensus, ray triangulation, camera height)",
    "no ground": "no metric scale: no ground plane and no ray-implied scale",
    "inconsistent motion": "the pose lies outside the caller's odometry gate (PoseGate), or, verified, "
    "outside the prior of its state estimate",
    "unverified": "the images do not confirm the pose (verify_pose: epipolar support, gravity, height)",
    "ambiguous": "the images confirm a distinct rival pose as well (e.g. identical rooms)",
}
TIMING_KEYS = (
    "retrieval",
    "backbone",
    "motion_averaging",
    "scale_recovery",
    "verification",
    "occupancy",
    "total",
)
#: Perception modes (DESIGN.md "Perception modes") -> what they do; the registry every setting and
#: report names a mode from.
PERCEPTION_MODES = {
    "paper": "every frame perceived on its own, as published (ground anchored once)",
    "temporal": "tracking: references around the pose an EKF predicts from action odometry, global "
    "retrieval to relocalize; the EKF gates the fixes, detects kidnapping, and its prior places poses among "
    "identical places; only trusted frames are mapped",
}


@dataclass(frozen=True)
class PerceptionConfig:
    """All pipeline settings; the ablation switches are ``retrieval.method`` (geometry | topk),
    ``averaging.method`` (weighted | single) and ``scale.enabled``.

    ``camera_height``: the calibrated camera-to-base height (metres), the metric anchor.
    ``verify``: the checks and second chances of :mod:`vgpnav_env.perception.verify`.
    """

    retrieval: RetrievalConfig = field(default_factory=RetrievalConfig)
    averaging: MotionAveragingConfig = field(default_factory=MotionAveragingConfig)
    scale: ScaleConfig = field(default_factory=ScaleConfig)
    occupancy: OccupancyConfig = field(default_factory=OccupancyConfig)
    verify: VerifyConfig = field(default_factory=VerifyConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    depth: PosedDepthConfig = field(default_factory=PosedDepthConfig)
    camera_height: float = CAMERA_HEIGHT

    def __post_init__(self) -> None:
        if not self.camera_height > 0:
            raise ValueError(f"camera_height must be positive metres, got {self.camera_height}")

    @classmethod
    def ablation(
        cls,
        *,
        retrieval: str = "geometry",
        averaging: str = "weighted",
        scale: bool = True,
        k: int = 10,
        camera_height: float = CAMERA_HEIGHT,
        rerank: int = RetrievalConfig.rerank,
    ) -> PerceptionConfig:
        """The default config with the three ablation switches set (and ``k`` references, ``rerank``
        candidates re-ranked by geometry)."""
        return cls(
            retrieval=RetrievalConfig(k=k, method=retrieval, rerank=rerank),
            averaging=MotionAveragingConfig(method=averaging),
            scale=ScaleConfig(enabled=scale),
            camera_height=camera_height,
        )


@dataclass(frozen=True)
class PerceptionResult:
    """One frame's navigation-ready state (immutable; the fused map is :attr:`Perceiver.map`).

    ``T_wc``: metric camera pose (4x4, OpenCV camera -> world); None when lost before a pose was
    estimated (a pose rejected afterwards is kept for inspection). ``points_w`` (N, 3) float32
    metric world points of the query (confident, subsampled pixels; empty when lost) and their
    ``classes`` (free ground / obstacle masks). ``references``: database indices used, best
    match first. ``scale``: metres per backbone unit (nan when lost, or localized without a scale:
    then no points) and ``scale_source`` (ground | fallback | disabled | none). ``z_ground``:
    anchored floor height (W, metres).
    ``timings``: wall seconds per stage (:data:`TIMING_KEYS`) and ``cpu``: the process's CPU
    seconds for the whole call (all threads; less sensitive than wall time to other processes
    sharing the cores). ``detail`` says why a frame was lost, or which second chance placed it.
    ``retrieved``: the references retrieval chose (the first round; ``references`` may come from
    a second round). ``verdict``: what the images say about the pose (None when no pose was
    verified) and ``confidence`` its :attr:`~vgpnav_env.perception.verify.Verdict.confidence`
    (0 when lost): how much to trust the pose. ``source``: where the references came from,
    ``tracking`` (around the caller's predicted pose) or ``global`` (retrieval over the database).
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
    retrieved: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    verdict: Verdict | None = None
    confidence: float = 0.0
    source: str = "global"

    @property
    def localized(self) -> bool:
        return self.status == "localized"

    @property
    def prior_placed(self) -> bool:
        """Localized only thanks to the caller's ``prior`` (:attr:`Verdict.by_prior`: the images
        alone would not confirm the pose): a state estimator may take it in, a map should not (such
        poses skip the plane check and may sit a decimetre off: fused, they can close a doorway)."""
        return self.localized and self.verdict is not None and self.verdict.by_prior

    @property
    def measurement(self) -> NDArray[np.float64] | None:
        """The pose a state estimator takes in: ``T_wc`` when localized, or when the images verified
        it and only the caller's ``prior`` rejected it ("inconsistent motion": the estimator counts
        it toward relocalizing, should its estimate be the wrong one); else None."""
        verified = self.verdict is not None and self.verdict.ok
        if self.localized or (self.reason == "inconsistent motion" and verified):
            return self.T_wc
        return None


@dataclass(frozen=True)
class _Localization:
    """Stages 1-3 of one frame: references, backbone output and motion-averaging result (the pose
    in W, its translation at the rays' scale); ``reason`` is a lost reason, "" when localized;
    ``retrieved``: the first round's references; ``source``: tracking or global; ``other``: the
    references and backbone output of the round that lost (None: one round), which verification
    checks the pose against too."""

    references: NDArray[np.int64]
    backbone: BackboneOutput | None = None
    motion: MotionResult | None = None
    n_confident_pairs: int = 0
    reason: str = ""
    detail: str = ""
    retrieved: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    source: str = "global"
    other: tuple[NDArray[np.int64], BackboneOutput] | None = None

    @property
    def ok(self) -> bool:
        return not self.reason


@dataclass(frozen=True)
class _MetricPose:
    """Stage 4 of one frame: the metric ``T_wc``, its scale (metres per backbone unit), the ground
    peak it came from and the anchored floor height (nan before the anchor is set); ``anchor``: the
    provisional anchor this pose set (the perceiver had none), kept only if the pose is verified."""

    T_wc: NDArray[np.float64]
    scale: ScaleEstimate
    ground: GroundEstimate | None = None
    z_ground: float = float("nan")
    anchor: GroundAnchor | None = None


class _Clock:
    """Wall seconds per stage (:data:`TIMING_KEYS`), the process CPU seconds per stage (``<stage>_cpu``,
    all threads) and the CPU seconds of one ``perceive`` call (``cpu``); steps inside a stage are
    ``<stage>.<step>`` (and ``<stage>.<step>_cpu``), summed over the call (e.g. both backbone rounds)."""

    def __init__(self) -> None:
        stages = TIMING_KEYS[:-1]
        self.timings = dict.fromkeys(TIMING_KEYS, 0.0) | dict.fromkeys([f"{k}_cpu" for k in stages], 0.0)
        self._start, self._cpu = time.perf_counter(), time.process_time()

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        t0, cpu0 = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            self.add({name: time.perf_counter() - t0, f"{name}_cpu": time.process_time() - cpu0})

    def add(self, timings: dict[str, float], stage: str | None = None) -> None:
        """Add ``timings`` (seconds by key) to this call's, as steps of ``stage`` when given."""
        for key, seconds in timings.items():
            key = f"{stage}.{key}" if stage else key
            self.timings[key] = self.timings.get(key, 0.0) + seconds

    def stop(self) -> dict[str, float]:
        total, cpu = time.perf_counter() - self._start, time.process_time() - self._cpu
        return self.timings | {"total": total, "cpu": cpu}


class Perceiver:
    """Stateful VGP-Nav perception for one robot episode.

    ``backbone``: a :class:`Backbone` or a registry name (built with
    :func:`~vgpnav_env.perception.backbones.make_backbone` for ``database``). ``camera`` defaults
    to the database camera (query images must have its size). :attr:`map` is the fused log-odds
    map of the episode (the live object). Call :meth:`reset` per episode, optionally
    :meth:`initialize` with frames taken standing still (else the first localized frame anchors
    the ground), then :meth:`perceive` per frame. ``privileged`` (simulated backbone only)
    carries the query's true ``T_wq`` and depth; the references' ``T_wi`` are filled in here
    from the database.
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

    def reset(self, anchor: GroundAnchor | None = None) -> None:
        """Forget the episode: a fresh map from the prior and no ground anchor, or a copy of
        ``anchor`` (e.g. one initialised by another perceiver of the same sequence)."""
        self.map = self.database.new_map(self.config.occupancy)
        self.anchor = copy.deepcopy(anchor) if anchor is not None else GroundAnchor(self.config.scale)

    @property
    def initialized(self) -> bool:
        return self.anchor.initialized

    def initialize(
        self,
        images: Sequence[NDArray[np.uint8]] | NDArray[np.uint8],
        privileged: Sequence[Privileged | None] | Privileged | None = None,
    ) -> list[PerceptionResult]:
        """Anchor the ground from frames taken while the robot stands still (paper "Ground Height
        Initialization"): ``z_ground = mean(t_wc.z) - camera_height`` over the frames whose motion
        averaging succeeded. Then every frame is perceived (and fused) with the anchor. If none
        localizes (verified), the anchor is dropped: poses the images do not confirm set no floor
        (a wrong floor fails every right pose after it on the camera-height check); the first
        verified :meth:`perceive` sets it. Frames that fail the mount check against the map's floor
        anchor nothing (:meth:`_map_camera_z`).
        """
        if isinstance(images, np.ndarray) and images.ndim == 3:
            images = [images]
        priv = privileged if isinstance(privileged, Sequence) else [privileged] * len(images)
        if len(priv) != len(images):
            raise ValueError(f"got {len(priv)} privileged entries for {len(images)} images")
        observations = []
        for rgb, p in zip(images, priv, strict=True):
            loc = self._localize(rgb, p, _Clock())
            if loc.ok and not implausible_mount(loc.motion.T_wq, self._map_camera_z(), self.config.verify):
                observations.append((loc.motion.T_wq, None))
        if observations:
            self.anchor.initialize(observations, self.config.camera_height)
        results = [self.perceive(rgb, p) for rgb, p in zip(images, priv, strict=True)]
        if not any(r.localized for r in results):
            self.anchor = GroundAnchor(self.config.scale)
        return results

    def perceive(
        self,
        rgb: NDArray[np.uint8],
        privileged: Privileged | None = None,
        gate: PoseGate | None = None,
        *,
        predicted: NDArray[np.float64] | None = None,
        prior: PoseGate | None = None,
        fuse: bool = True,
    ) -> PerceptionResult:
        """Perceive one RGB frame (uint8 HxWx3 of the camera's size) and fuse it into :attr:`map`.

        With a ``gate``, a pose outside it is lost ("inconsistent motion"), nothing is fused.
        ``predicted`` (tracking): a predicted camera pose ``T_wc`` (4x4); the references are chosen
        among the database cameras near it (:func:`tracked_references`; none near: lost), else by
        global retrieval. One tracked attempt per frame: after a lost tracked frame the caller relocalizes
        on the next (:meth:`~vgpnav_env.perception.state.EKFState.tracking_pose`).
        ``prior``: where a state estimate confidently expects the camera
        (:meth:`~vgpnav_env.perception.state.EKFState.prior`); unlike ``gate`` it rejects nothing,
        a pose inside it needs less from the images (:func:`verify_pose`).
        ``fuse=False``: the caller fuses the frame later if it trusts it (:meth:`fuse`).
        A frame lost with a ``prior`` gets two more chances, both verified by the images with it: a
        global attempt (no ``predicted``) a second one with references around the prior's pose
        (:meth:`_prior_camera`), a tracked one without database cameras near ``predicted`` a global
        one; then a pose placed inside the prior (:meth:`_place_on_prior`, marked
        :attr:`PerceptionResult.prior_placed`).
        """
        clock = _Clock()
        result, points_w = self._attempt(rgb, privileged, gate, clock, predicted, prior)
        lost = [result] if prior is not None and result.reason != "inconsistent motion" else []
        if lost and not result.localized and self.anchor.initialized:
            # Global references lost: those around the prior's pose; none near the predicted pose:
            # global ones (a tracked attempt that ran its backbone gets no second one).
            around = self._prior_camera(prior) if predicted is None else None
            if predicted is None or result.backbone is None:
                again, again_points = self._attempt(rgb, privileged, gate, clock, around, prior)
                if again.localized or again.backbone is not None:
                    result, points_w = again, again_points
                    lost = [again, *lost] if again.reason != "inconsistent motion" else []
        for attempt in lost if not result.localized else []:
            with clock.stage("verification"):
                placed = self._place_on_prior(attempt, prior, gate)
            if placed is not None:
                result, points_w = placed
                break
        if result.localized:
            with clock.stage("occupancy"):
                posed = self._posed_points(rgb, result, points_w, clock)
            if posed is not None:
                result, points_w = replace(result, points_w=posed.astype(np.float32)), posed
        if result.localized and fuse:
            with clock.stage("occupancy"), clock.stage("occupancy.fusion"):
                result = replace(result, classes=self._fuse(result, points_w))
        return replace(result, timings=clock.stop())

    def _posed_points(
        self, rgb: NDArray[np.uint8], result: PerceptionResult, points_w: NDArray[np.float64], clock: _Clock
    ) -> NDArray[np.float64] | None:
        """The localized frame's metric points from the depth swept again at its pose
        (:mod:`~vgpnav_env.perception.posed_depth`, ``config.depth``) against the classical
        backbone's sweep references and the database cameras that see its first ``points_w`` best;
        None (keep ``points_w``) when off, for other backbones, or without points."""
        cfg, net, out = self.config.depth, self.backbone, result.backbone
        if not cfg.enabled or not isinstance(net, ClassicalBackbone) or out is None or len(points_w) == 0:
            return None
        db, T_wc, occ = self.database, result.T_wc, self.config.occupancy
        own = result.references[net.select_sweep_references(out.confidence, out.scale_valid, out.T_iq)]
        refs = posed_references(T_wc, db.poses, own, points_w, self.camera, cfg)
        if len(refs) == 0:
            return None
        depths = ((points_w - T_wc[:3, 3]) @ T_wc[:3, :3])[:, 2]
        sweep: dict[str, float] = {}
        with clock.stage("occupancy.posed_depth"):
            depth, confidence = posed_depth(
                rgb, [db.images[i] for i in refs], db.poses[refs], T_wc, self.camera, depths,
                cfg.sweep, threads=net.config.threads, timings=sweep,
            )  # fmt: skip
        # The completion apart from the sweep proper.
        clock.add(
            {
                "posed_depth": -sweep.get("completion", 0.0),
                "posed_depth_cpu": -sweep.get("completion_cpu", 0.0),
            },
            "occupancy",
        )
        clock.add(sweep, "occupancy")
        points_q, _ = depth_points(
            self.camera,
            depth,
            confidence,
            stride=occ.point_stride,
            min_confidence=occ.min_confidence,
            max_depth=occ.max_depth,
        )
        return transform_points(T_wc, points_q)

    def fuse(self, result: PerceptionResult) -> PointClasses:
        """Fuse a localized frame's metric points into :attr:`map` (stage 5); their classes."""
        return self._fuse(result, result.points_w.astype(np.float64))

    def _fuse(self, result: PerceptionResult, points_w: NDArray[np.float64]) -> PointClasses:
        occ = self.config.occupancy
        return self.map.update(
            points_w,
            result.z_ground,
            self.config.camera_height,
            camera_xy=result.T_wc[:2, 3],
            free_tol=occ.free_tol,
            obstacle_min=occ.obstacle_min,
            clear_height=occ.clear_height,
            min_cell_points=occ.min_cell_points,
            max_obstacle_range=occ.max_obstacle_range,
            protect_free=occ.protect_free,
        )

    def _attempt(
        self,
        rgb: NDArray[np.uint8],
        privileged: Privileged | None,
        gate: PoseGate | None,
        clock: _Clock,
        predicted: NDArray[np.float64] | None,
        prior: PoseGate | None = None,
    ) -> tuple[PerceptionResult, NDArray[np.float64] | None]:
        """Stages 1-4 and verification of one frame (not fused: ``classes`` None) and its metric
        points (None when lost); references around ``predicted`` (None: global retrieval); a
        tracking attempt without near cameras is lost."""
        guide = predicted if prior is not None else None  # a confident prediction guides the pairs
        loc = self._localize(rgb, privileged, clock, predicted, guide)  # stages 1-3
        if not loc.ok:
            loc = self._prior_consensus(loc, clock, prior)
        if not loc.ok:
            loc = self._single_pair_fallback(loc, clock)
        if not loc.ok:
            return _lost(loc, clock), None
        with clock.stage("scale_recovery"):  # stage 4
            loc, pose = self._recover_scale(loc, gate)
            points_w = self._points(loc, pose.T_wc, pose.scale) if loc.ok else None
        if not loc.ok:
            return _lost(loc, clock, T_wc=pose.T_wc, z_ground=pose.z_ground, ground=pose.ground), None
        with clock.stage("verification"):
            T_wc, verdict = self._verify(loc, pose, prior)
        rival = T_wc is not pose.T_wc
        if rival:  # the prior picked a rival: its pose and points
            pose = replace(pose, T_wc=T_wc)
            points_w = self._points(loc, T_wc, pose.scale)
            picked = "the prior picked a rival pose"
            loc = replace(loc, detail=f"{picked} ({loc.detail})" if loc.detail else picked)
        if verdict.ok and prior is not None and not prior.admits(pose.T_wc):
            distance, yaw = prior.deviation(pose.T_wc)
            detail = f"verified pose {distance:.2f} m / {np.degrees(yaw):.0f} deg from the prior's centre"
            loc = replace(loc, reason="inconsistent motion", detail=detail)
            lost = _lost(
                loc, clock, T_wc=pose.T_wc, z_ground=pose.z_ground, ground=pose.ground, verdict=verdict
            )
            return lost, None
        if verdict.ok and pose.anchor is not None and not self.anchor.initialized:
            self.anchor = pose.anchor  # the first verified pose anchors the ground
        if not verdict.ok:
            loc = replace(
                loc,
                reason=verdict.reason,
                detail=f"{verdict.detail} ({loc.detail})" if loc.detail else verdict.detail,
            )
            lost = _lost(
                loc, clock, T_wc=pose.T_wc, z_ground=pose.z_ground, ground=pose.ground, verdict=verdict
            )
            return lost, None
        if not rival and pose.anchor is None and prior is not None:
            with clock.stage("verification"):
                slid = self._slide(loc, pose, prior, gate)
            if slid is not None:
                pose, verdict, points_w = slid
        result = PerceptionResult(
            status="localized",
            reason="",
            T_wc=pose.T_wc,
            points_w=points_w.astype(np.float32),
            classes=None,
            references=loc.references,
            scale=pose.scale.scale,
            scale_source=pose.scale.source,
            z_ground=pose.z_ground,
            timings={},
            motion=loc.motion,
            ground=pose.ground,
            backbone=loc.backbone,
            n_confident_pairs=loc.n_confident_pairs,
            detail=loc.detail,
            retrieved=loc.retrieved,
            verdict=verdict,
            confidence=verdict.confidence,
            source=loc.source,
        )
        return result, points_w

    def _slide(
        self, loc: _Localization, pose: _MetricPose, prior: PoseGate | None, gate: PoseGate | None
    ) -> tuple[_MetricPose, Verdict, NDArray[np.float64]] | None:
        """The verified ``pose`` moved along the ray its position rests on (:func:`slide_on_ray`;
        the caller tries it only inside the EKF's ``prior``, which bounds the move),
        its scale corrected by the same factor, with its verdict and metric points, when the images
        verify it there (:meth:`_verify`, no rival taking its place) and the ``prior`` and the
        ``gate`` admit it; else None."""
        out = loc.backbone
        T_wi = self.database.poses[loc.references]
        moved = slide_on_ray(pose.T_wc, T_wi, out, loc.motion.weights, self.camera, self.config.verify)
        if moved is None:
            return None
        T, factor = moved
        if any(g is not None and not g.admits(T) for g in (prior, gate)):
            return None
        slid = replace(pose, T_wc=T, scale=replace(pose.scale, scale=pose.scale.scale * factor))
        T_checked, verdict = self._verify(loc, slid, prior)
        if T_checked is not T or not verdict.ok:
            return None
        return slid, verdict, self._points(loc, T, slid.scale)

    def _verify(
        self, loc: _Localization, pose: _MetricPose, prior: PoseGate | None = None
    ) -> tuple[NDArray[np.float64], Verdict]:
        """:func:`verify_pose` of the metric pose against the frame's references and those of the
        round that lost (:func:`pooled_pairs`), with the rival poses of the pairs it does not
        explain, or in small part (:func:`rival_pairs`, :func:`rival_poses`): the pose and its
        verdict. With a ``prior`` that the pose is not confirmed inside, the rival the prior picks
        (:func:`prior_hypothesis`) replaces it when there is one."""
        refs, out = loc.references, loc.backbone
        if loc.other is not None:
            refs, out = pooled_pairs(refs, out, *loc.other)
        T_wi = self.database.poses[refs]
        cfg = self.config
        v = cfg.verify
        # The pairs' own support (one epipolar count per pair) serves both rules that need it.
        uses_own = v.rival_claim_ratio is not None or v.min_explained_confidence is not None
        own = pair_support(T_wi, out, self.camera, v) if uses_own else None
        support = reference_support(pose.T_wc, T_wi, out, self.camera, v)
        support = rival_pairs(support, T_wi, out, self.camera, v, own)
        rivals = rival_poses(pose.T_wc, T_wi, out, support, pose.scale.scale, cfg.averaging)
        camera_z = pose.z_ground + cfg.camera_height  # nan before the ground is anchored
        map_z = self._map_camera_z()
        if pose.anchor is not None and np.isfinite(map_z):
            camera_z = map_z  # the pose would anchor the ground: the map's floor checks it
        verdict = verify_pose(
            pose.T_wc, T_wi, out, self.camera, v, rivals=rivals, camera_z=camera_z, own=own, prior=prior
        )
        if prior is None or (verdict.ok and prior.admits(pose.T_wc)):
            return pose.T_wc, verdict
        picked = prior_hypothesis(
            pose.T_wc, rivals, T_wi, out, self.camera, v, prior,
            scale=pose.scale.scale, averaging=cfg.averaging, camera_z=camera_z, own=own,
        )  # fmt: skip
        return (pose.T_wc, verdict) if picked is None else picked

    def _map_camera_z(self) -> float:
        """World height (metres) of a camera at the calibrated height above the floor the
        database's reconstruction found (:attr:`Database.z_ground`; nan when unknown). A pose that
        anchors the ground must stand there (:func:`implausible_mount`): a floor set too high fails
        every right pose after it on the camera-height check."""
        return float(self.database.z_ground) + self.config.camera_height

    def _localize(
        self,
        rgb: NDArray[np.uint8],
        privileged: Privileged | None,
        clock: _Clock,
        predicted: NDArray[np.float64] | None = None,
        guide: NDArray[np.float64] | None = None,
    ) -> _Localization:
        """Stages 1-3 (retrieval, backbone, motion averaging), with the second round of
        :func:`~vgpnav_env.perception.verify.second_round_references` when the first is weak;
        ``predicted``: references around that camera pose (tracking) instead of the whole database;
        ``guide``: the camera pose the backbone's pairs expect (:meth:`_round`)."""
        rgb = np.asarray(rgb)
        expected = (self.camera.height, self.camera.width, 3)
        if rgb.shape != expected or rgb.dtype != np.uint8:
            raise ValueError(f"query image must be uint8 with shape {expected}, got {rgb.dtype} {rgb.shape}")
        db, cfg = self.database, self.config
        with clock.stage("retrieval"):
            sims = np.nan_to_num(db.index.similarity(rgb), nan=-1.0, posinf=-1.0, neginf=-1.0)
            if predicted is not None:
                refs = tracked_references(sims, db.poses, predicted, self.camera, cfg.retrieval, cfg.tracking)
                source = "tracking"
            else:
                if cfg.retrieval.rerank:
                    sift = db.index.sift
                    query = rootsift(rgb, sift)
                    sims = geometric_rerank(sims, query, db.reference_features, cfg.retrieval, sift.ratio)
                refs, source = select_references(sims, db.poses, cfg.retrieval), "global"
        if len(refs) == 0:
            detail = "empty database" if predicted is None else "no database camera near the predicted pose"
            return _Localization(refs, reason="too few matches", detail=detail, source=source)
        retrieved, other = refs, None
        out, motion = self._round(rgb, refs, privileged, clock, guide)
        if cfg.averaging.method == "weighted":
            with clock.stage("retrieval"):
                second = second_round_references(
                    refs,
                    out,
                    motion,
                    sims,
                    db.poses,
                    cfg.verify,
                    k=cfg.retrieval.k,
                    consensus_deg=cfg.averaging.consensus_deg,
                    pair_scale=(lambda T: self._calibrated_scale(out, T)) if cfg.scale.enabled else None,
                )
            if len(second):
                out2, motion2 = self._round(rgb, second, privileged, clock, guide)
                logger.debug(
                    "second round: %s ok=%s (%s) -> %s ok=%s (%s)",
                    refs.tolist(),
                    motion.ok,
                    motion.reason,
                    second.tolist(),
                    motion2.ok,
                    motion2.reason,
                )
                if round_rank(out2, motion2) > round_rank(out, motion):
                    other = refs, out
                    refs, out, motion = second, out2, motion2
                else:
                    other = second, out2
        n_conf = int((out.confidence > 0).sum())
        if n_conf == 0:
            detail = f"no reference pair passed the backbone (matches {out.n_matches.tolist()})"
            return _Localization(
                refs, out, reason="too few matches", detail=detail, retrieved=retrieved, source=source
            )
        if not motion.ok:
            reason = "too few matches" if motion.reason == "too few references" else "no consensus"
            return _Localization(refs, out, motion, n_conf, reason, motion.reason, retrieved, source, other)
        return _Localization(refs, out, motion, n_conf, retrieved=retrieved, source=source, other=other)

    def _round(
        self,
        rgb: NDArray[np.uint8],
        refs: NDArray[np.int64],
        privileged: Privileged | None,
        clock: _Clock,
        guide: NDArray[np.float64] | None = None,
    ) -> tuple[BackboneOutput, MotionResult]:
        """Stages 2-3 over ``refs``: backbone, then motion averaging whose pose must pass the
        camera-height check. ``guide``: a camera pose ``T_wc`` the caller confidently predicts; the
        backbone gets the relative poses it implies (``expected_T_qi``) to guide its pairs."""
        db = self.database
        with clock.stage("backbone"):
            if privileged is not None:
                privileged = replace(privileged, T_wi=db.poses[refs], reference_depths=None)
            out = self.backbone(
                rgb,
                [db.images[i] for i in refs],
                self.camera,
                privileged=privileged,
                reference_keys=[int(i) for i in refs],
                expected_T_qi=None if guide is None else invert_pose(guide) @ db.poses[refs],
            )
        clock.add(out.timings, "backbone")
        with clock.stage("motion_averaging"):
            cfg = self.config
            motion = average_motion(
                db.poses[refs], out.T_qi, out.confidence, cfg.averaging, scale_valid=out.scale_valid
            )
            motion = check_height(motion, self.anchor, cfg.camera_height, cfg.verify)
        return out, motion

    def _prior_consensus(self, loc: _Localization, clock: _Clock, prior: PoseGate | None) -> _Localization:
        """``loc`` re-averaged over its pairs that agree with the ``prior`` (:func:`prior_pairs`), at
        least two, when motion averaging over all of them failed; else unchanged."""
        if prior is None or loc.motion is None or loc.backbone is None:
            return loc
        cfg, out = self.config, loc.backbone
        T_wi = self.database.poses[loc.references]
        with clock.stage("motion_averaging"):
            agree = prior_pairs(T_wi, out, prior)
            if agree.sum() < 2:
                return loc
            confidence = np.where(agree, out.confidence, 0.0)
            motion = average_motion(T_wi, out.T_qi, confidence, cfg.averaging, scale_valid=out.scale_valid)
            motion = check_height(motion, self.anchor, cfg.camera_height, cfg.verify)
        if not motion.ok:
            return loc
        return replace(
            loc, motion=motion, reason="", detail=f"pairs agreeing with the prior after: {loc.detail}"
        )

    def _prior_camera(self, prior: PoseGate) -> NDArray[np.float64]:
        """The camera pose ``T_wc`` of a robot at the ``prior``'s planar pose: the calibrated camera
        height above the anchored ground, the database cameras' median pitch (the same mount)."""
        pitch = float(np.median([camera_yaw_pitch(T)[1] for T in self.database.poses]))
        return camera_T_wc(prior.pose, float(self.anchor.z_ground) + self.config.camera_height, pitch)

    def _place_on_prior(
        self, lost: PerceptionResult, prior: PoseGate, gate: PoseGate | None
    ) -> tuple[PerceptionResult, NDArray[np.float64]] | None:
        """A ``lost`` frame placed inside the ``prior`` (:func:`prior_poses`) when :func:`verify_pose`
        with the prior confirms that pose with at least ``min_supporting_references`` (and 2)
        references that explain :func:`prior_support_floor` matches together: the strongest such
        pose, localized and marked :attr:`PerceptionResult.prior_placed`, and its metric points;
        else None. Its scale is the ground's, checked against the supporting pairs' (their distance
        to the pose over their backbone translation, median); without a ground peak the pose comes
        with no points."""
        out, refs = lost.backbone, lost.references
        if out is None or out.matches is None or not self.anchor.initialized:
            return None  # without matches a reference's support is a 10 deg test: no placement
        if not (out.confidence > 0).any():
            return None
        cfg, v = self.config, self.config.verify
        T_wi = self.database.poses[refs]
        camera_z = float(self.anchor.z_ground) + cfg.camera_height
        hypotheses = prior_poses(T_wi, out, self.camera, prior, camera_z, v)
        if not hypotheses:
            return None
        uses_own = v.rival_claim_ratio is not None or v.min_explained_confidence is not None
        own = pair_support(T_wi, out, self.camera, v) if uses_own else None
        baseline = np.linalg.norm(out.T_iq[:, :3, 3], axis=1)
        best = None
        if out.matches is not None:
            refined = [
                refine_pose(T, T_wi, out.matches, self.camera, v, max_shift=prior.max_distance)
                for T in hypotheses
            ]
            hypotheses += [T for T in refined if prior.admits(T)]
        for T in hypotheses:
            distance = np.linalg.norm(T_wi[:, :3, 3] - T[:3, 3], axis=1)
            support = reference_support(T, T_wi, out, self.camera, v)
            usable = (
                (support >= v.min_support_matches) & out.scale_valid & (baseline > 0) & (out.confidence > 0)
            )
            if not usable.any():
                continue
            pair_scale = float(np.median(distance[usable] / baseline[usable]))
            support = rival_pairs(support, T_wi, out, self.camera, v, own)
            rivals = rival_poses(T, T_wi, out, support, pair_scale, cfg.averaging)
            verdict = verify_pose(
                T, T_wi, out, self.camera, v, rivals=rivals, camera_z=camera_z, own=own, prior=prior
            )
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
        ground = self._ground(out, T, self.anchor.expected_height_b(T, pair_scale))
        scale = self.anchor.scale_for(T, ground, fallback_scale=pair_scale)
        scale = check_scale(scale, pair_scale, v, weight, ground)
        scale = plausible_scale(scale, self._median_depth(out), v)
        if not scale.ok:
            return None
        # A placed pose without the ground's scale has no metric depth to map (the supporting
        # pairs' scale puts its points decimetres to metres off).
        ground_scale = scale.source == "ground"
        points_w = self._metric_points(out, T, scale.scale) if ground_scale else np.zeros((0, 3))
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
            z_ground=float(self.anchor.z_ground),
            ground=ground,
            detail=detail,
            verdict=replace(verdict, by_prior=True),
            confidence=verdict.confidence,
        )
        return result, points_w

    def _single_pair_fallback(self, loc: _Localization, clock: _Clock) -> _Localization:
        """``loc`` placed by its most confident pair (:func:`single_pair_fallback`), else unchanged."""
        if loc.motion is None or loc.backbone is None or not self.config.scale.enabled:
            return loc
        with clock.stage("motion_averaging"):
            motion = single_pair_fallback(
                loc.references, loc.backbone, self.database.poses, self.config.averaging, self.config.verify
            )
        if motion is None:
            return loc
        return replace(loc, motion=motion, reason="", detail=f"single-pair fallback after: {loc.detail}")

    def _recover_scale(self, loc: _Localization, gate: PoseGate | None) -> tuple[_Localization, _MetricPose]:
        """Stage 4: the metric pose and scale of a localized frame, and ``loc`` (lost when the pose
        is outside ``gate``, its scale implausible, or a single pair's pose has no ground scale; a
        pose the rays placed stands without any scale: scale "none", no points). Without an anchor,
        the pose anchors the ground provisionally (the returned pose's ``anchor``; :meth:`_attempt`
        keeps it once verified)."""
        single = loc.motion.reason == "single reference" and self.config.scale.enabled
        T_wc, scale, ground = self._place_single(loc) if single else (loc.motion.T_wq, None, None)
        if gate is not None and not gate.admits(T_wc):
            distance, yaw = gate.deviation(T_wc)
            detail = (
                f"pose {distance:.2f} m / {np.degrees(yaw):.0f} deg from the expected one "
                f"(gate {gate.max_distance:.2f} m / {np.degrees(gate.max_yaw):.0f} deg)"
            )
            none = ScaleEstimate(float("nan"), "none")
            return replace(loc, reason="inconsistent motion", detail=detail), _MetricPose(T_wc, none)
        anchor, provisional = self.anchor, None
        if not anchor.initialized and (scale is None or scale.ok):
            anchor = provisional = GroundAnchor(self.config.scale)
            anchor.initialize([(T_wc, None)], self.config.camera_height)
        if scale is None:
            scale, ground = self._ground_scale(loc, T_wc, anchor)
        found = scale
        scale = plausible_scale(scale, self._median_depth(loc.backbone), self.config.verify)
        z_ground = float(anchor.z_ground) if anchor.initialized else float("nan")
        pose = _MetricPose(T_wc, scale, ground, z_ground, provisional)
        if not found.ok and not single:
            # The rays placed the pose in metres (the references' known poses); only the depth has no
            # scale: verification judges the pose, and it maps nothing.
            detail = "no ground peak and no ray-implied scale: no points"
            return replace(loc, detail=f"{detail} ({loc.detail})" if loc.detail else detail), pose
        if not scale.ok:
            detail = (
                f"{found.source} scale {found.scale:.3g} m per unit puts the median depth nearer "
                f"than {self.config.verify.min_median_depth_m} m"
                if found.ok
                else "no ground peak and no ray-implied scale"
            )
            return replace(loc, reason="no ground", detail=detail), pose
        return loc, pose

    def _place_single(self, loc: _Localization) -> tuple[NDArray[np.float64], ScaleEstimate, GroundEstimate]:
        """Stage 4 for a single-reference pose: the ground scale at the calibrated camera height
        places the camera along the pair's ray (the single-view baseline); scale "none" when no
        ground is seen (the pose stays at backbone scale)."""
        out, motion = loc.backbone, loc.motion
        ground = self._ground(out, motion.T_wq, None)
        if not ground.found:
            return motion.T_wq, ScaleEstimate(float("nan"), "none"), ground
        scale = self.config.camera_height / -ground.height_b
        i = int(np.argmax(motion.weights))
        T_wc = motion.T_wq.copy()
        T_wc[:3, 3] = pair_centre(self.database.poses[loc.references[i]], out.T_iq[i], scale)
        return T_wc, ScaleEstimate(scale, "ground"), ground

    def _ground_scale(
        self, loc: _Localization, T_wc: NDArray[np.float64], anchor: GroundAnchor
    ) -> tuple[ScaleEstimate, GroundEstimate]:
        """Stage 4: the ground peak near the height the rays' scale predicts (else the dominant peak),
        scaled to the camera height above the ``anchor``'s ground, checked against the rays' scale."""
        out, ray_scale = loc.backbone, loc.motion.scale_from_rays
        prior = None
        if anchor.initialized and self.config.scale.enabled:
            prior = anchor.expected_height_b(T_wc, ray_scale)
        ground = self._ground(out, T_wc, prior)
        if prior is not None and not ground.found:
            # Nothing near the ray-implied height: the rays' scale may be off (a weak pair);
            # the dominant ground peak counts if it passes the scale check against them.
            ground = self._ground(out, T_wc, None)
        scale = anchor.scale_for(T_wc, ground, fallback_scale=ray_scale)
        ray_weight = float(loc.motion.weights.sum())
        return check_scale(scale, ray_scale, self.config.verify, ray_weight, ground), ground

    def _calibrated_scale(self, out: BackboneOutput, T_wc: NDArray[np.float64]) -> float | None:
        """Metres per backbone unit that put the ground peak at the calibrated camera height below
        a camera oriented as ``T_wc`` (None when no ground is seen)."""
        ground = self._ground(out, T_wc, None)
        return self.config.camera_height / -ground.height_b if ground.found else None

    def _ground(
        self, out: BackboneOutput, T_wc: NDArray[np.float64], prior_height_b: float | None
    ) -> GroundEstimate:
        """Ground peak (backbone units) of the whole reconstruction: confident query pixels plus the
        reference depths a backbone returns (moved into the query frame, weighted by pair confidence
        on the common scale). ``prior_height_b`` restricts the peak to near the expected height."""
        occ = self.config.occupancy
        weights = out.confidence * out.scale_valid if out.reference_depths is not None else None
        points, w = reconstruction_points(
            self.camera,
            out.query_depth,
            out.query_depth_confidence,
            out.T_qi,
            out.reference_depths,
            weights,
            stride=occ.point_stride,
            min_confidence=occ.min_confidence,
        )
        return ground_peak(points, T_wc[:3, :3], w, self.config.scale, prior_height_b=prior_height_b)

    def _median_depth(self, out: BackboneOutput) -> float:
        """Median query depth (backbone units) of the confident pixels (nan when none)."""
        depth = out.query_depth[(out.query_depth_confidence >= self.config.occupancy.min_confidence)]
        depth = depth[np.isfinite(depth) & (depth > 0)]
        return float(np.median(depth)) if len(depth) else float("nan")

    def _points(
        self, loc: _Localization, T_wc: NDArray[np.float64], scale: ScaleEstimate
    ) -> NDArray[np.float64]:
        """The metric points of a localized frame at ``T_wc``: none without a ``scale``."""
        return self._metric_points(loc.backbone, T_wc, scale.scale) if scale.ok else np.zeros((0, 3))

    def _metric_points(
        self, out: BackboneOutput, T_wc: NDArray[np.float64], scale: float
    ) -> NDArray[np.float64]:
        """Stage 5's input: the confident query points at ``scale`` within ``max_depth``, in W."""
        occ = self.config.occupancy
        points_q, _ = depth_points(
            self.camera,
            out.query_depth,
            out.query_depth_confidence,
            stride=occ.point_stride,
            min_confidence=occ.min_confidence,
        )
        points_q = points_q[points_q[:, 2] * scale <= occ.max_depth]
        return recover_metric_points(points_q, T_wc, scale)


def _lost(loc: _Localization, clock: _Clock, **kw) -> PerceptionResult:
    """The lost result of ``loc`` (its reason and detail); ``kw``: the pose and ground found before
    the frame was rejected, if any."""
    return PerceptionResult(
        status="lost",
        reason=loc.reason,
        T_wc=kw.pop("T_wc", None),
        points_w=np.zeros((0, 3), np.float32),
        classes=None,
        references=loc.references,
        scale=float("nan"),
        scale_source="none",
        z_ground=kw.pop("z_ground", float("nan")),
        timings=clock.stop(),
        motion=loc.motion,
        backbone=loc.backbone,
        n_confident_pairs=loc.n_confident_pairs,
        detail=loc.detail,
        retrieved=loc.retrieved,
        source=loc.source,
        **kw,
    )


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
