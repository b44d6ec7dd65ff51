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
from typing import Any

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
    metric_centre,
    pair_centre,
)
from vgpnav_env.perception.occupancy import OccupancyConfig, PointClasses
from vgpnav_env.perception.points import depth_points
from vgpnav_env.perception.posed_depth import PosedDepthConfig, RecentFrames, posed_depth, posed_references
from vgpnav_env.perception.recovery import (
    RECOVERY,
    Attempt,
    Frame,
    Outcome,
    Phase,
    RecoveryConfig,
    pooled_pairs,
    second_round,
)
from vgpnav_env.perception.resection import ResectionConfig, resect
from vgpnav_env.perception.resolution import downscale, working_size
from vgpnav_env.perception.retrieval import (
    RetrievalConfig,
    TrackingConfig,
    geometric_rerank,
    select_references,
    tracked_references,
    twin_references,
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
    LOST_REASONS,
    LostReason,
    Pairs,
    PoseGate,
    Verdict,
    VerifyCheck,
    VerifyConfig,
    assess,
    check_height,
    check_scale,
    distinct,
    implausible_mount,
    plausible_scale,
    prior_hypothesis,
)
from vgpnav_env.robot import CAMERA_HEIGHT, camera_T_wc

logger = logging.getLogger(__name__)

__all__ = [
    "LOST_REASONS",
    "PERCEPTION_MODES",
    "TIMING_KEYS",
    "Perceiver",
    "PerceptionConfig",
    "PerceptionResult",
    "perceive",
]
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
    ``verify``: the checks of :mod:`vgpnav_env.perception.verify`; ``recovery``: the second
    chances of :mod:`vgpnav_env.perception.recovery`; ``resection``: stage 4's refinement of a
    metric pose (:mod:`vgpnav_env.perception.resection`; None: off).
    """

    retrieval: RetrievalConfig = field(default_factory=RetrievalConfig)
    averaging: MotionAveragingConfig = field(default_factory=MotionAveragingConfig)
    scale: ScaleConfig = field(default_factory=ScaleConfig)
    occupancy: OccupancyConfig = field(default_factory=OccupancyConfig)
    verify: VerifyConfig = field(default_factory=VerifyConfig)
    recovery: RecoveryConfig = field(default_factory=RecoveryConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    depth: PosedDepthConfig = field(default_factory=PosedDepthConfig)
    resection: ResectionConfig | None = field(default_factory=ResectionConfig)
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
class Localization:
    """Stages 1-3 of one frame: references, backbone output and motion-averaging result (the pose
    in W, its translation at the rays' scale); ``reason`` is a lost reason, "" when localized;
    ``retrieved``: the first round's references; ``source``: tracking or global; ``other``: the
    references and backbone output of the round that lost (None: one round), which verification
    checks the pose against too; ``similarity`` (M,): retrieval's scores of the database images;
    ``guide``: the camera pose the backbone's pairs were guided by."""

    references: NDArray[np.int64]
    backbone: BackboneOutput | None = None
    motion: MotionResult | None = None
    n_confident_pairs: int = 0
    reason: str = ""
    detail: str = ""
    retrieved: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    source: str = "global"
    other: tuple[NDArray[np.int64], BackboneOutput] | None = None
    similarity: NDArray[np.float64] | None = None
    guide: NDArray[np.float64] | None = None

    @property
    def ok(self) -> bool:
        return not self.reason


@dataclass(frozen=True)
class MetricPose:
    """Stage 4 of one frame: the metric ``T_wc``, its scale (metres per backbone unit), the ground
    peak it came from and the anchored floor height (nan before the anchor is set); ``anchor``: the
    provisional anchor this pose set (the perceiver had none), kept only if the pose is verified."""

    T_wc: NDArray[np.float64]
    scale: ScaleEstimate
    ground: GroundEstimate | None = None
    z_ground: float = float("nan")
    anchor: GroundAnchor | None = None


class Clock:
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
    :func:`~vgpnav_env.perception.backbones.make_backbone` for ``database``). ``camera``: the query
    camera, which must work at the database camera's size (:mod:`~vgpnav_env.perception.resolution`:
    a wider one's images are downscaled to it; default: the database camera). :attr:`camera` is the
    database camera, the one perception works with. :attr:`map` is the fused log-odds
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
        self.camera = database.camera
        query = camera or database.camera
        size = working_size(query.width, query.height, database.config.max_width)
        if size != (self.camera.width, self.camera.height):
            raise ValueError(
                f"query camera {query.width}x{query.height} differs from the database camera "
                f"{self.camera.width}x{self.camera.height}; build both at the same size"
            )
        self.config = config or PerceptionConfig()
        self.reset()

    def reset(self, anchor: GroundAnchor | None = None) -> None:
        """Forget the episode: a fresh map from the prior and no ground anchor, or a copy of
        ``anchor`` (e.g. one initialised by another perceiver of the same sequence)."""
        self.map = self.database.new_map(self.config.occupancy)
        self.anchor = copy.deepcopy(anchor) if anchor is not None else GroundAnchor(self.config.scale)
        # Floors a pose's height is checked against, until poses refute them (_refutes_floor): the
        # map's (before the anchor) and an anchor no pose of another place has confirmed yet.
        self._floor_votes: list[NDArray[np.float64]] = []
        self._map_floor_refuted = False
        self._anchored_by: list[NDArray[np.float64]] = []  # the poses that set an unconfirmed anchor
        self.recent = RecentFrames(self.config.depth.recent_frames)

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
            frame = self._frame(rgb, p, None, None, None, Clock())
            loc = self._localize(frame)
            loc = second_round(self, frame, loc) or loc
            if loc.ok and not implausible_mount(loc.motion.T_wq, self._map_camera_z(), self.config.verify):
                observations.append((loc.motion.T_wq, None))
        if observations:
            self.anchor.initialize(observations, self.config.camera_height)
            self._anchored_by = [T for T, _ in observations]
        results = [self.perceive(rgb, p) for rgb, p in zip(images, priv, strict=True)]
        if not any(r.localized for r in results):
            self.anchor, self._anchored_by = GroundAnchor(self.config.scale), []
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
        """Perceive one RGB frame (uint8 HxWx3 of the query camera's size) and fuse it into :attr:`map`.

        With a ``gate``, a pose outside it is lost ("inconsistent motion"), nothing is fused.
        ``predicted`` (tracking): a predicted camera pose ``T_wc`` (4x4); the references are chosen
        among the database cameras near it (:func:`tracked_references`; none near: lost), else by
        global retrieval. One tracked attempt per frame: after a lost tracked frame the caller relocalizes
        on the next (:meth:`~vgpnav_env.perception.state.EKFState.tracking_pose`).
        ``prior``: where a state estimate confidently expects the camera
        (:meth:`~vgpnav_env.perception.state.EKFState.prior`); unlike ``gate`` it rejects nothing,
        a pose inside it needs less from the images (:func:`verify_pose`).
        ``fuse=False``: the caller fuses the frame later if it trusts it (:meth:`fuse`).

        Stages 1-4 and verification run in :meth:`attempt`; a frame they do not place verified gets
        the recovery strategies of :data:`~vgpnav_env.perception.recovery.RECOVERY` in order (their
        :attr:`~vgpnav_env.perception.recovery.Phase.POSE` ones inside :meth:`attempt`); then stage
        5 maps a localized frame.
        """
        clock = Clock()
        frame = self._frame(rgb, privileged, gate, predicted, prior, clock)
        first = self.attempt(frame, predicted)  # stages 1-4, verification
        lost = (first,) if prior is not None and first.result.reason != LostReason.INCONSISTENT_MOTION else ()
        outcome = Outcome(first, lost)
        for strategy in RECOVERY:
            if strategy.phase is Phase.RESULT:
                outcome = strategy.run(self, frame, outcome) or outcome
        result, points_w = outcome.attempt.result, outcome.attempt.points_w
        if result.localized:
            with clock.stage("occupancy"):  # stage 5
                posed = self._posed_points(rgb, result, points_w, clock)
            if posed is not None:
                result, points_w = replace(result, points_w=posed.astype(np.float32)), posed
        if result.localized and fuse:
            with clock.stage("occupancy"), clock.stage("occupancy.fusion"):
                result = replace(result, classes=self._fuse(result, points_w))
        return replace(result, timings=clock.stop())

    def _posed_points(
        self, rgb: NDArray[np.uint8], result: PerceptionResult, points_w: NDArray[np.float64], clock: Clock
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
        live, T_live = self.recent.select(T_wc, points_w, self.camera, cfg)
        refs = posed_references(T_wc, db.poses, own, points_w, self.camera, cfg, cfg.references - len(live))
        if len(refs) + len(live) == 0:
            return None
        depths = ((points_w - T_wc[:3, 3]) @ T_wc[:3, :3])[:, 2]
        sweep: dict[str, float] = {}
        with clock.stage("occupancy.posed_depth"):
            depth, confidence = posed_depth(
                rgb, [*live, *(db.images[i] for i in refs)], np.concatenate([T_live, db.poses[refs]]), T_wc,
                self.camera, depths, cfg.sweep, threads=net.config.threads, timings=sweep,
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

    def fuse(self, result: PerceptionResult, rgb: NDArray[np.uint8] | None = None) -> PointClasses:
        """Fuse a localized frame's metric points into :attr:`map` (stage 5); their classes. With
        the frame's ``rgb``, the frame, whose pose the caller trusts, joins :attr:`recent`: a
        reference of the map's sweep for the frames after it."""
        if rgb is not None:
            self.recent.add(rgb, result.T_wc)
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

    def attempt(self, frame: Frame, predicted: NDArray[np.float64] | None) -> Attempt:
        """Stages 1-4 and verification of one frame (not fused: ``classes`` None), with the
        :attr:`~vgpnav_env.perception.recovery.Phase.POSE` recovery strategies after stage 3;
        references around ``predicted`` (None: global retrieval; a tracking attempt without near
        cameras is lost)."""
        clock, prior, gate = frame.clock, frame.prior, frame.gate
        guide = predicted if prior is not None else None  # a confident prediction guides the pairs
        loc = self._localize(frame, predicted, guide)  # stages 1-3
        for strategy in RECOVERY:
            if strategy.phase is Phase.POSE:
                loc = strategy.run(self, frame, loc) or loc
        if not loc.ok:
            return Attempt(_lost(loc, clock), None, loc)
        with clock.stage("scale_recovery"):  # stage 4
            loc, pose = self._recover_scale(loc, gate)
            points_w = self.points(loc, pose.T_wc, pose.scale) if loc.ok else None
        if not loc.ok:
            lost = _lost(loc, clock, T_wc=pose.T_wc, z_ground=pose.z_ground, ground=pose.ground)
            return Attempt(lost, None, loc, pose)
        anchor = self.anchor
        with clock.stage("verification"):
            T_wc, verdict = self.verify(loc, pose, prior, frame)
        rival = T_wc is not pose.T_wc
        if self.anchor is not anchor:  # the pose refuted the anchored floor: its scale anew
            with clock.stage("scale_recovery"):
                loc, rescaled = self._recover_scale(loc, gate)
                pose = replace(rescaled, T_wc=pose.T_wc)
                points_w = self.points(loc, pose.T_wc, pose.scale) if loc.ok else None
        if rival:  # the prior picked a rival: its pose and points
            pose = replace(pose, T_wc=T_wc)
            points_w = self.points(loc, T_wc, pose.scale)
            picked = "the prior picked a rival pose"
            loc = replace(loc, detail=f"{picked} ({loc.detail})" if loc.detail else picked)
        if verdict.ok and prior is not None and not prior.admits(pose.T_wc):
            distance, yaw = prior.deviation(pose.T_wc)
            detail = f"verified pose {distance:.2f} m / {np.degrees(yaw):.0f} deg from the prior's centre"
            loc = replace(loc, reason=LostReason.INCONSISTENT_MOTION, detail=detail)
        elif not verdict.ok:
            detail = f"{verdict.detail} ({loc.detail})" if loc.detail else verdict.detail
            loc = replace(loc, reason=verdict.reason, detail=detail)
        if not loc.ok:
            kw = {"T_wc": pose.T_wc, "z_ground": pose.z_ground, "ground": pose.ground, "verdict": verdict}
            return Attempt(_lost(loc, clock, **kw), None, loc, pose, rival)
        if pose.anchor is not None and not self.anchor.initialized:
            self.anchor, self._anchored_by = pose.anchor, [pose.T_wc]  # the first verified pose anchors
        elif self._anchored_by and all(distinct(pose.T_wc, T, self.config.verify) for T in self._anchored_by):
            self._anchored_by, self._floor_votes = [], []  # a pose of another place confirms the anchor
        result = _result(
            loc,
            status="localized",
            reason="",
            T_wc=pose.T_wc,
            points_w=points_w.astype(np.float32),
            scale=pose.scale.scale,
            scale_source=pose.scale.source,
            z_ground=pose.z_ground,
            timings={},
            ground=pose.ground,
            verdict=verdict,
            confidence=verdict.confidence,
        )
        return Attempt(result, points_w, loc, pose, rival)

    def twin_pairs(
        self,
        frame: Frame,
        loc: Localization,
        refs: NDArray[np.int64],
        pairs: Pairs,
        T_wc: NDArray[np.float64],
    ) -> Pairs | None:
        """``pairs`` (the frame's pairs for verification, with the database images ``refs``) and
        the query's pairs with the ``RetrievalConfig.twins``
        :func:`~vgpnav_env.perception.retrieval.twin_references` of the global pose ``T_wc``: a twin
        of the place elsewhere is then a rival with comparable support. None without any."""
        cfg, db = self.config, self.database
        if loc.similarity is None:
            return None
        twins = twin_references(
            loc.similarity, db.poses, T_wc, self.camera, refs, cfg.retrieval.twins, cfg.tracking
        )
        if len(twins) == 0:
            return None
        both = np.concatenate([loc.references, twins])
        # Within the verification stage; the backbone has the references' pairs cached.
        out = self.reconstruct(frame, both, depth=False)
        return self.pairs(*pooled_pairs(refs, pairs.out, both, out))

    def verify(
        self, loc: Localization, pose: MetricPose, prior: PoseGate | None = None, frame: Frame | None = None
    ) -> tuple[NDArray[np.float64], Verdict]:
        """:func:`~vgpnav_env.perception.verify.assess` of the metric pose against the frame's
        references and those of the round that lost (:func:`pooled_pairs`): the pose and its
        verdict. A pose the images confirm from global references without a ``prior`` is judged
        again with the pairs of its place's twins (:meth:`twin_pairs`; needs the ``frame``). With a
        ``prior`` that the pose is not confirmed inside, the rival the prior picks
        (:func:`prior_hypothesis`) replaces it when there is one."""
        refs, out = loc.references, loc.backbone
        if loc.other is not None:
            refs, out = pooled_pairs(refs, out, *loc.other)
        pairs = self.pairs(refs, out)
        cfg = self.config
        camera_z = pose.z_ground + cfg.camera_height  # nan before the ground is anchored
        map_z = self._map_camera_z()
        anchoring = pose.anchor is not None and np.isfinite(map_z) and not self._map_floor_refuted
        if anchoring:
            camera_z = map_z  # the pose would anchor the ground: the map's floor checks it

        def verdict_at(z: float):
            return assess(
                pose.T_wc, pairs, scale=pose.scale.scale, averaging=cfg.averaging, camera_z=z, prior=prior
            )

        a = verdict_at(camera_z)
        unconfirmed = pose.anchor is None and bool(self._anchored_by)
        if (anchoring or unconfirmed) and a.verdict.check == VerifyCheck.MOUNT:
            own = verdict_at(float(pose.T_wc[2, 3]))  # the mount's roll and pitch only
            # The map's floor stands on the whole database: it takes more poses to refute.
            needed = 3 if anchoring else len(self._anchored_by) + 1
            if own.verdict.ok and self._refutes_floor(pose.T_wc, needed):
                a, camera_z = own, float(pose.T_wc[2, 3])
                if anchoring:
                    self._map_floor_refuted = True
                else:  # the pose anchors the ground anew
                    self.anchor = GroundAnchor(cfg.scale)
                    self.anchor.initialize([(pose.T_wc, None)], cfg.camera_height)
                    self._anchored_by = [pose.T_wc]
        if prior is None and frame is not None and a.verdict.ok and loc.source == "global":
            twinned = self.twin_pairs(frame, loc, refs, pairs, pose.T_wc)
            if twinned is not None:
                pairs = twinned
                a = verdict_at(camera_z)
        if prior is None or (a.verdict.ok and prior.admits(pose.T_wc)):
            return pose.T_wc, a.verdict
        picked = prior_hypothesis(
            pose.T_wc, a.rivals, pairs, prior, scale=pose.scale.scale, averaging=cfg.averaging,
            camera_z=camera_z,
        )  # fmt: skip
        return (pose.T_wc, a.verdict) if picked is None else picked

    def _refutes_floor(self, T_wc: NDArray[np.float64], needed: int) -> bool:
        """Count ``T_wc``, a pose the images verify but for its camera height against a floor (the
        map's before the ground is anchored, or an anchor no pose of another place has confirmed),
        as a vote against that floor: refuted once ``needed`` such poses -- ``T_wc`` and others of
        another place (:func:`~vgpnav_env.perception.verify.distinct`) -- agree on the camera height within
        ``pose_height_tolerance``. A wrong floor (a reconstruction's, or one anchored by a wrong
        first pose) would otherwise reject every right pose after it, and the episode would never
        localize."""
        v = self.config.verify
        tol = v.pose_height_tolerance if v.pose_height_tolerance is not None else np.inf
        agree = [T for T in self._floor_votes if distinct(T, T_wc, v) and abs(T[2, 3] - T_wc[2, 3]) <= tol]
        refuted = len(agree) + 1 >= needed
        self._floor_votes = [] if refuted else [*self._floor_votes, np.asarray(T_wc, float).copy()]
        return refuted

    def pairs(self, references: NDArray[np.int64], out: BackboneOutput) -> Pairs:
        """The query's pairs with the database images ``references`` (``out``: the backbone output
        with exactly these), for verification."""
        return Pairs(self.database.poses[references], out, self.camera, self.config.verify)

    def _map_camera_z(self) -> float:
        """World height (metres) of a camera at the calibrated height above the floor the
        database's reconstruction found (:attr:`Database.z_ground`; nan when unknown). A pose that
        anchors the ground must stand there (:func:`implausible_mount`): a floor set too high fails
        every right pose after it on the camera-height check."""
        return float(self.database.z_ground) + self.config.camera_height

    def _frame(
        self,
        rgb: NDArray[np.uint8],
        privileged: Privileged | None,
        gate: PoseGate | None,
        predicted: NDArray[np.float64] | None,
        prior: PoseGate | None,
        clock: Clock,
    ) -> Frame:
        """The :class:`~vgpnav_env.perception.recovery.Frame` of one call, its image (and the
        simulated backbone's depth) downscaled to :attr:`camera` when the query camera is wider
        (:mod:`~vgpnav_env.perception.resolution`; any other size fails in :meth:`_localize`)."""
        rgb = np.asarray(rgb)
        size = (self.camera.width, self.camera.height)
        h, w = rgb.shape[:2]
        if rgb.ndim == 3 and (w, h) != size and working_size(w, h, self.database.config.max_width) == size:
            rgb = downscale(rgb, self.camera)
            if privileged is not None:
                depths = privileged.reference_depths
                privileged = replace(
                    privileged,
                    query_depth=downscale(np.asarray(privileged.query_depth), self.camera, nearest=True),
                    reference_depths=None
                    if depths is None
                    else np.stack([downscale(d, self.camera, nearest=True) for d in np.asarray(depths)]),
                )
        return Frame(rgb, privileged, gate, predicted, prior, clock)

    def _localize(
        self,
        frame: Frame,
        predicted: NDArray[np.float64] | None = None,
        guide: NDArray[np.float64] | None = None,
    ) -> Localization:
        """Stages 1-3 (retrieval, backbone, motion averaging) of one round; ``predicted``:
        references around that camera pose (tracking) instead of the whole database; ``guide``:
        the camera pose the backbone's pairs expect (:meth:`round`)."""
        rgb, clock = frame.rgb, frame.clock
        expected = (self.camera.height, self.camera.width, 3)
        if rgb.shape != expected or rgb.dtype != np.uint8:
            raise ValueError(f"query image must be uint8 with shape {expected}, got {rgb.dtype} {rgb.shape}")
        db, cfg = self.database, self.config
        with clock.stage("retrieval"):  # stage 1
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
            return Localization(refs, reason=LostReason.TOO_FEW_MATCHES, detail=detail, source=source)
        loc = Localization(refs, retrieved=refs, source=source, similarity=sims, guide=guide)
        return self.conclude(loc, *self.round(frame, refs, guide))  # stages 2-3

    def conclude(self, loc: Localization, out: BackboneOutput, motion: MotionResult) -> Localization:
        """``loc`` with the backbone output and motion averaging of its ``references``, lost when no
        pair passed the backbone or motion averaging failed."""
        n_conf = int((out.confidence > 0).sum())
        loc = replace(loc, backbone=out, motion=motion, n_confident_pairs=n_conf, reason="", detail="")
        if n_conf == 0:
            detail = f"no reference pair passed the backbone (matches {out.n_matches.tolist()})"
            return replace(loc, reason=LostReason.TOO_FEW_MATCHES, detail=detail)
        if not motion.ok:
            few = motion.reason == "too few references"
            reason = LostReason.TOO_FEW_MATCHES if few else LostReason.NO_CONSENSUS
            return replace(loc, reason=reason, detail=motion.reason)
        return loc

    def round(
        self, frame: Frame, refs: NDArray[np.int64], guide: NDArray[np.float64] | None = None
    ) -> tuple[BackboneOutput, MotionResult]:
        """Stages 2-3 over ``refs``: backbone, then motion averaging whose pose must pass the
        camera-height check. ``guide``: a camera pose ``T_wc`` the caller confidently predicts; the
        backbone gets the relative poses it implies (``expected_T_qi``) to guide its pairs."""
        clock = frame.clock
        with clock.stage("backbone"):
            out = self.reconstruct(frame, refs, guide)
        clock.add(out.timings, "backbone")
        with clock.stage("motion_averaging"):
            cfg, T_wi = self.config, self.database.poses[refs]
            motion = average_motion(
                T_wi, out.T_qi, out.confidence, cfg.averaging, scale_valid=out.scale_valid
            )
            motion = check_height(motion, self.anchor, cfg.camera_height, cfg.verify)
        return out, motion

    def reconstruct(
        self,
        frame: Frame,
        refs: NDArray[np.int64],
        guide: NDArray[np.float64] | None = None,
        depth: bool = True,
    ) -> BackboneOutput:
        """The backbone's output for the frame's query and the database images ``refs`` (stage 2,
        untimed: the caller's stage counts it); ``guide`` as in :meth:`round`; ``depth`` False: the
        pairs only (the backbone may skip the query depth)."""
        db, privileged = self.database, frame.privileged
        if privileged is not None:
            privileged = replace(privileged, T_wi=db.poses[refs], reference_depths=None)
        return self.backbone(
            frame.rgb,
            [db.images[i] for i in refs],
            self.camera,
            privileged=privileged,
            reference_keys=[int(i) for i in refs],
            expected_T_qi=None if guide is None else invert_pose(guide) @ db.poses[refs],
            depth=depth,
        )

    def prior_camera(self, prior: PoseGate) -> NDArray[np.float64]:
        """The camera pose ``T_wc`` of a robot at the ``prior``'s planar pose: the calibrated camera
        height above the anchored ground, the database cameras' median pitch (the same mount)."""
        pitch = float(np.median([camera_yaw_pitch(T)[1] for T in self.database.poses]))
        return camera_T_wc(prior.pose, float(self.anchor.z_ground) + self.config.camera_height, pitch)

    def _recover_scale(self, loc: Localization, gate: PoseGate | None) -> tuple[Localization, MetricPose]:
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
            return replace(loc, reason="inconsistent motion", detail=detail), MetricPose(T_wc, none)
        anchor, provisional = self.anchor, None
        if not anchor.initialized and (scale is None or scale.ok):
            anchor = provisional = GroundAnchor(self.config.scale)
            anchor.initialize([(T_wc, None)], self.config.camera_height)
        if scale is None:
            scale, ground = self._ground_scale(loc, T_wc, anchor)
        found = scale
        scale = plausible_scale(scale, self.median_depth(loc.backbone), self.config.verify)
        if scale.ok and scale.source != "disabled" and not single:
            # The pairs' metric distances place the centre along the rays too.
            out, T_wi, averaging = loc.backbone, self.database.poses[loc.references], self.config.averaging
            T_wc = metric_centre(loc.motion, T_wi, out.T_iq, scale.scale, out.scale_valid, averaging)
            if self.config.resection is not None and out.matches is not None:
                # Points the references triangulate place the camera by reprojection.
                resected = resect(T_wc, T_wi, out.matches, self.camera, self.config.resection).T_wq
                T_wc = T_wc if resected is None else resected
            if provisional is not None:
                provisional.initialize([(T_wc, None)], self.config.camera_height)
        z_ground = float(anchor.z_ground) if anchor.initialized else float("nan")
        pose = MetricPose(T_wc, scale, ground, z_ground, provisional)
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

    def _place_single(self, loc: Localization) -> tuple[NDArray[np.float64], ScaleEstimate, GroundEstimate]:
        """Stage 4 for a single-reference pose: the ground scale at the calibrated camera height
        places the camera along the pair's ray (the single-view baseline); scale "none" when no
        ground is seen (the pose stays at backbone scale)."""
        out, motion = loc.backbone, loc.motion
        ground = self.ground(out, motion.T_wq, None)
        if not ground.found:
            return motion.T_wq, ScaleEstimate(float("nan"), "none"), ground
        scale = self.config.camera_height / -ground.height_b
        i = int(np.argmax(motion.weights))
        T_wc = motion.T_wq.copy()
        T_wc[:3, 3] = pair_centre(self.database.poses[loc.references[i]], out.T_iq[i], scale)
        return T_wc, ScaleEstimate(scale, "ground"), ground

    def _ground_scale(
        self, loc: Localization, T_wc: NDArray[np.float64], anchor: GroundAnchor
    ) -> tuple[ScaleEstimate, GroundEstimate]:
        """Stage 4: the ground peak near the height the rays' scale predicts (else the dominant peak),
        scaled to the camera height above the ``anchor``'s ground, checked against the rays' scale."""
        out, ray_scale = loc.backbone, loc.motion.scale_from_rays
        prior = None
        if anchor.initialized and self.config.scale.enabled:
            prior = anchor.expected_height_b(T_wc, ray_scale)
        ground = self.ground(out, T_wc, prior)
        if prior is not None and not ground.found:
            # Nothing near the ray-implied height: the rays' scale may be off (a weak pair);
            # the dominant ground peak counts if it passes the scale check against them.
            ground = self.ground(out, T_wc, None)
        scale = anchor.scale_for(T_wc, ground, fallback_scale=ray_scale)
        ray_weight = float(loc.motion.weights.sum())
        return check_scale(scale, ray_scale, self.config.verify, ray_weight, ground), ground

    def calibrated_scale(self, out: BackboneOutput, T_wc: NDArray[np.float64]) -> float | None:
        """Metres per backbone unit that put the ground peak at the calibrated camera height below
        a camera oriented as ``T_wc`` (None when no ground is seen)."""
        ground = self.ground(out, T_wc, None)
        return self.config.camera_height / -ground.height_b if ground.found else None

    def ground(
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

    def median_depth(self, out: BackboneOutput) -> float:
        """Median query depth (backbone units) of the confident pixels (nan when none)."""
        depth = out.query_depth[(out.query_depth_confidence >= self.config.occupancy.min_confidence)]
        depth = depth[np.isfinite(depth) & (depth > 0)]
        return float(np.median(depth)) if len(depth) else float("nan")

    def points(
        self, loc: Localization, T_wc: NDArray[np.float64], scale: ScaleEstimate
    ) -> NDArray[np.float64]:
        """The metric points of a localized frame at ``T_wc``: none without a ``scale``."""
        return self.metric_points(loc.backbone, T_wc, scale.scale) if scale.ok else np.zeros((0, 3))

    def metric_points(
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


def _result(loc: Localization, **fields: Any) -> PerceptionResult:
    """The result of a frame that went through ``loc`` (its references, motion, backbone output,
    confident pairs, detail, retrieval and source; no ``classes`` until fused) with the other
    ``fields``."""
    return PerceptionResult(
        classes=None,
        references=loc.references,
        motion=loc.motion,
        backbone=loc.backbone,
        n_confident_pairs=loc.n_confident_pairs,
        detail=loc.detail,
        retrieved=loc.retrieved,
        source=loc.source,
        **fields,
    )


def _lost(loc: Localization, clock: Clock, **kw) -> PerceptionResult:
    """The lost result of ``loc`` (its reason and detail); ``kw``: the pose and ground found before
    the frame was rejected, if any."""
    return _result(
        loc,
        status="lost",
        reason=loc.reason,
        T_wc=kw.pop("T_wc", None),
        points_w=np.zeros((0, 3), np.float32),
        scale=float("nan"),
        scale_source="none",
        z_ground=kw.pop("z_ground", float("nan")),
        timings=clock.stop(),
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
