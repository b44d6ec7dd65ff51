"""Running VGP-Nav perception over a build's query run and scoring every frame.

Shared by the localization, perception, timing and ablation protocols:

- :func:`add_scene_arguments` / :func:`resolve_build`: ``SCENE`` + ``--build DIR`` (else the scene
  is built, or reused, with :func:`vgpnav_env.build.build_runs` in the default cache directory);
- :func:`perceive_queries`: the one loop of these protocols; a :class:`QueryRun` (build, backbone,
  pipeline config, frames, seed) runs one :class:`~vgpnav_env.perception.pipeline.Perceiver` over an
  evenly spaced subset of the query run and yields a :class:`QueryFrame` per frame; each protocol
  only computes its metrics (:func:`localization_metrics`, :func:`perception_metrics`, ...) and
  report from them. The ground anchor is initialised on the first query frame (the
  robot standing still) with that frame's camera height as the calibrated camera-to-base height
  (the query run jitters the camera height per frame by +-0.05 m around the nominal 1.2 m; a robot
  knows its own, and anchoring with the nominal value instead biased every metric scale by ~3%),
  and persists. Per frame: pose error
  against the run's true pose, and Acc / Comp of the predicted metric points against the true
  visible surface (ground-truth depth back-projected with the true pose; read here for
  evaluation only, and for the privileged ``simulated`` backbone).

Acc = mean nearest-neighbour distance predicted -> true, Comp = true -> predicted (metres), from
a seeded subsample of ``max_points`` of one set to all points of the other; both sets keep only
points at most ``max_depth`` metres in front of the camera (the perception range). Predicted
points are every second pixel (``OccupancyConfig.point_stride``) with confident depth; the true
surface is every pixel with finite depth.
"""

from __future__ import annotations

import argparse
import logging
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from vgpnav_env.arguments import count_arg, positive_int_arg, unit_interval_arg
from vgpnav_env.eval.workers import Workers, note
from vgpnav_env.geometry import camera_yaw_pitch, rotation_angle, wrap_angle
from vgpnav_env.perception.backbones import BACKBONES, Backbone, Privileged, make_backbone
from vgpnav_env.perception.database import Database, DatabaseConfig, open_database
from vgpnav_env.perception.feature_choice import FeatureChoice, cached_choice
from vgpnav_env.perception.motion_averaging import AVERAGING_METHODS
from vgpnav_env.perception.odometry import VisualOdometry, fuse_motion
from vgpnav_env.perception.pipeline import Perceiver, PerceptionConfig, PerceptionResult
from vgpnav_env.perception.resolution import describe_size
from vgpnav_env.perception.retrieval import RETRIEVAL_METHODS, RetrievalConfig, nearby_cameras
from vgpnav_env.perception.scale_recovery import GroundAnchor
from vgpnav_env.perception.state import EKFState
from vgpnav_env.perception.verify import PoseGate
from vgpnav_env.robot import base_pose, camera_T_wc
from vgpnav_env.runs import Build, load_build, load_run_depth, read_build_summary, read_run_meta

logger = logging.getLogger(__name__)

#: (translation metres, rotation degrees) thresholds of the recall metrics (DESIGN.md "Metrics").
RECALL_THRESHOLDS = {
    "recall_5cm_5deg": (0.05, 5.0),
    "recall_25cm_2deg": (0.25, 2.0),
    "recall_50cm_5deg": (0.50, 5.0),
}
#: A localized frame farther off than this (metres, degrees) is a gross error.
GROSS_ERROR = (0.5, 10.0)
#: Retrieval found the place when a chosen reference lies within (metres, degrees) of the true pose.
RETRIEVAL_HIT = (1.0, 45.0)


def add_scene_arguments(
    parser: argparse.ArgumentParser, *, queries: int | None = 50, several: bool = False
) -> None:
    """``SCENE`` (``several``: one or more, ``args.scene`` is then a list), ``--build``, ``--size``,
    ``--seed``, ``--texture``, ``--out``, ``--queries``."""
    from vgpnav_env.arguments import count_arg, seed_arg, size_arg
    from vgpnav_env.scenes import TEXTURE_LEVELS

    what = "built-in scene name (home, hospital, home:SEED, hospital:SEED) or a scene spec file"
    if several:
        parser.add_argument("scene", nargs="+", help=f"one or more: {what}; ignored with --build")
    else:
        parser.add_argument("scene", help=f"{what} (ignored with --build)")
    if several:
        parser.add_argument(
            "--build",
            type=Path,
            nargs="+",
            metavar="DIR",
            help="existing build directories, one per scene in order (default: build or reuse them)",
        )
    else:
        parser.add_argument(
            "--build", type=Path, help="an existing build directory (default: build or reuse one)"
        )
    parser.add_argument(
        "--size", type=size_arg, default=(320, 240), metavar="WxH", help="image size (default 320x240)"
    )
    parser.add_argument("--seed", type=seed_arg, default=0, help="trajectory seed of the build (default 0)")
    parser.add_argument(
        "--texture",
        choices=TEXTURE_LEVELS,
        default="realistic",
        help="texture level of the build (default realistic)",
    )
    parser.add_argument("--out", type=Path, required=True, help="report directory")
    parser.add_argument(
        "--queries",
        type=count_arg,
        default=queries,
        help=f"number of evenly spaced query frames, 0 = all (default {queries or 'all'})",
    )


def add_backbone_arguments(parser: argparse.ArgumentParser) -> None:
    """``--backbone`` (a :data:`BACKBONES` name), ``--model`` and ``--weights`` (``learned`` only);
    read them with :func:`backbone_options`."""
    parser.add_argument(
        "--backbone", choices=sorted(BACKBONES), default="classical", help="default classical"
    )
    parser.add_argument(
        "--model", metavar="MODULE:FACTORY", help="learned backbone: the model factory, e.g. mypkg.vggt:model"
    )
    parser.add_argument(
        "--weights", type=Path, metavar="PATH", help="learned backbone: a local checkpoint (never downloaded)"
    )
    parser.add_argument(
        "--features",
        choices=("rootsift", "xfeat"),
        help="classical backbone: its local features (default: ClassicalConfig's)",
    )
    parser.add_argument(
        "--matcher",
        choices=("nearest", "lighterglue"),
        help="classical backbone: nearest neighbours or LighterGlue (XFeat) (default: ClassicalConfig's)",
    )
    parser.add_argument(
        "--fallback-pairs",
        type=int,
        metavar="N",
        help="classical backbone with RootSIFT: when too few pairs pass, match up to N failed pairs "
        "again with XFeat + LighterGlue, 0 = off (default: ClassicalConfig's)",
    )
    parser.add_argument(
        "--fallback-min-pairs",
        type=positive_int_arg,
        metavar="M",
        help="classical backbone: the fallback runs when fewer than M RootSIFT pairs pass "
        "(default: ClassicalConfig's)",
    )
    parser.add_argument(
        "--switch-share",
        type=unit_interval_arg,
        metavar="S",
        help="classical backbone: match every pair with XFeat + LighterGlue where RootSIFT gets fewer "
        "than S of the database's own overlapping pairs right and XFeat significantly more; "
        "0 = never (default: ClassicalConfig's)",
    )


def add_perception_mode_argument(parser: argparse.ArgumentParser, default: str = "temporal") -> None:
    """``--perception-mode`` (a :data:`~vgpnav_env.perception.pipeline.PERCEPTION_MODES` name)."""
    from vgpnav_env.perception.pipeline import PERCEPTION_MODES

    modes = "; ".join(f"{k}: {v}" for k, v in PERCEPTION_MODES.items())
    parser.add_argument(
        "--perception-mode",
        choices=list(PERCEPTION_MODES),
        default=default,
        help=f"default {default}. {modes}",
    )


def backbone_options(args: argparse.Namespace) -> dict[str, Any]:
    """The ``make_backbone`` options of ``--model`` / ``--weights`` (``--features`` / ``--matcher`` /
    ``--fallback-pairs`` / ``--fallback-min-pairs`` / ``--switch-share`` for the classical
    backbone); a one-line ValueError when they are missing for ``--backbone learned``, or given for
    another backbone."""
    names = ("features", "matcher", "fallback_pairs", "fallback_min_pairs", "switch_share")
    features = {k: v for k in names if (v := getattr(args, k, None)) is not None}
    if features and args.backbone != "classical":
        raise ValueError(
            "--features, --matcher, --fallback-pairs, --fallback-min-pairs and --switch-share are for "
            f"--backbone classical, not {args.backbone}"
        )
    if args.backbone != "learned":
        if args.model is not None or args.weights is not None:
            raise ValueError(f"--model and --weights are for --backbone learned, not {args.backbone}")
        return features
    if args.model is None or args.weights is None:
        raise ValueError(
            "--backbone learned needs --model MODULE:FACTORY and --weights PATH (a local checkpoint)"
        )
    if not args.weights.is_file():
        raise ValueError(f"--weights {args.weights}: no such file (the learned backbone never downloads)")
    return {"model": args.model, "weights_path": args.weights}


def classical_features(options: Mapping[str, Any], choice: FeatureChoice | None = None) -> str:
    """The classical backbone's features and matcher with ``options`` (the ``ClassicalConfig``
    fields), for reports, e.g. ``rootsift + nearest, XFeat + LighterGlue fallback (4 pairs when
    fewer than 3 pass)``; with the database's ``choice``
    (:func:`~vgpnav_env.perception.feature_choice.choose_features`) the features it chose and why."""
    from vgpnav_env.perception.backbones import ClassicalConfig

    config = options.get("config") or ClassicalConfig(**options)
    if choice is not None and choice.features == "xfeat":
        config = config.switch_config()
    text = f"{config.features} + {config.matcher}"
    if config.uses_fallback:
        text += (
            f", XFeat + LighterGlue fallback ({config.fallback_pairs} pairs when fewer than "
            f"{config.fallback_min_pairs} pass)"
        )
    if choice is not None:
        text += f"; scene check: {choice.describe()}"
    return text


def add_pipeline_arguments(parser: argparse.ArgumentParser) -> None:
    """``--backbone`` (with ``--model`` / ``--weights``), ``--retrieval``, ``--averaging``, ``--k``,
    ``--rerank``."""
    add_backbone_arguments(parser)
    parser.add_argument("--retrieval", choices=RETRIEVAL_METHODS, default="geometry", help="default geometry")
    parser.add_argument("--averaging", choices=AVERAGING_METHODS, default="weighted", help="default weighted")
    parser.add_argument("--k", type=positive_int_arg, default=10, help="number of references (default 10)")
    parser.add_argument(
        "--rerank",
        type=count_arg,
        default=RetrievalConfig.rerank,
        metavar="N",
        help="re-rank the N most similar database images by verified feature matches before the "
        f"selection, 0 = off (default {RetrievalConfig.rerank})",
    )
    parser.add_argument(
        "--verification",
        choices=["rules", "model"],
        default="rules",
        help="who accepts a pose: the rules of VerifyConfig, or the calibrated model (default rules)",
    )


def resolve_build(args: argparse.Namespace, scene: str | None = None, build: Path | None = None) -> Path:
    """The build directory: ``build`` (default ``--build``) or the (possibly new) default build of
    ``scene`` (default ``SCENE``)."""
    build = args.build if build is None else build
    if build is not None:
        read_build_summary(build)  # a missing or damaged build fails here, before any work
        return Path(build)
    from vgpnav_env.build import build_runs, default_build_dir

    scene = args.scene if scene is None else scene
    out = default_build_dir(scene, tuple(args.size), args.seed, args.texture)
    build_runs(scene, out, size=tuple(args.size), seed=args.seed, texture=args.texture)
    return out


def query_subset(n_frames: int, n: int | None) -> NDArray[np.int64]:
    """``n`` evenly spaced frame indices of ``n_frames`` (all when ``n`` is None, 0 or >= n_frames)."""
    if n is not None and n < 0:
        raise ValueError(f"the number of queries must be >= 0 (0 = all), got {n}")
    if not n or n >= n_frames:
        return np.arange(n_frames, dtype=np.int64)
    return np.unique(np.linspace(0, n_frames - 1, n).round().astype(np.int64))


def accuracy_completeness(
    pred: NDArray[np.floating], gt: NDArray[np.floating], rng: np.random.Generator, max_points: int = 4000
) -> tuple[float, float]:
    """(Acc, Comp) in metres: mean NN distance pred -> gt and gt -> pred (nan if either is empty).

    The distances are measured from at most ``max_points`` (seeded subsample) of each set to ALL
    points of the other set, so that the sampling density adds no floor to the errors.
    """
    if len(pred) == 0 or len(gt) == 0:
        return float("nan"), float("nan")

    def sample(points: NDArray[np.floating]) -> NDArray[np.floating]:
        return (
            points[rng.choice(len(points), max_points, replace=False)] if len(points) > max_points else points
        )

    acc = float(cKDTree(gt).query(sample(pred))[0].mean())
    comp = float(cKDTree(pred).query(sample(gt))[0].mean())
    return acc, comp


@dataclass
class FrameRecord:
    """One query frame's outcome (errors nan when lost).

    ``translation_m`` / ``rotation_deg``: error of the localized pose; ``candidate_*``: error of the
    pose the pipeline estimated before it rejected it (lost frames; equal to the errors above
    when localized, nan when no pose was estimated), to tell right rejections from wrong ones.
    ``retrieval_hit``: one of the ``retrieved`` database indices lies within
    :data:`RETRIEVAL_HIT` of the true pose; ``references``: the indices the pose came from.
    ``confidence``: the verification's confidence in the pose (0 when lost);
    ``candidate_confidence``: the probability the calibrated model gives the candidate pose (its
    verdict's score without a model; nan without a verdict).
    ``source``: where the references came from (``tracking`` around the predicted pose, or
    ``global`` retrieval). ``gate``: what rejected a lost frame, its ``reason`` or, when the
    verification rejected its pose as unverified, ``unverified: <check>``
    (:data:`~vgpnav_env.perception.verify.VERIFY_CHECKS`); "" when localized. Temporal mode
    only: ``fix``, what the EKF did with the frame's pose
    (:data:`~vgpnav_env.perception.state.FIX_OUTCOMES`), and ``estimate_error_m``, the horizontal
    error of the EKF's estimate after the frame (nan before its first estimate), and
    ``visual_odometry``, whether visual odometry refined the motion into the frame;
    ``prior_placed``: localized only thanks to the estimate's prior
    (:attr:`~vgpnav_env.perception.pipeline.PerceptionResult.prior_placed`).
    ``evidence``: the verification's :class:`~vgpnav_env.perception.verify.Evidence` of the
    candidate pose by field name ({} without a verdict): the data the calibrated model is fitted on.
    """

    frame: int
    status: str
    reason: str
    translation_m: float
    rotation_deg: float
    acc_m: float
    comp_m: float
    scale_source: str
    n_references: int
    n_confident_pairs: int
    n_points: int
    timings: dict[str, float] = field(default_factory=dict)
    detail: str = ""
    candidate_translation_m: float = float("nan")
    candidate_rotation_deg: float = float("nan")
    retrieval_hit: bool = False
    retrieved: list[int] = field(default_factory=list)
    references: list[int] = field(default_factory=list)
    confidence: float = 0.0
    candidate_confidence: float = float("nan")
    source: str = "global"
    fix: str = ""
    estimate_error_m: float = float("nan")
    visual_odometry: bool = False
    gate: str = ""
    prior_placed: bool = False
    evidence: dict[str, float] = field(default_factory=dict)

    @property
    def gross(self) -> bool:
        """Localized and more than :data:`GROSS_ERROR` off."""
        return self.status == "localized" and is_gross(self.translation_m, self.rotation_deg)


def is_gross(translation_m, rotation_deg):
    """Whether errors (metres, degrees; scalars or arrays) exceed :data:`GROSS_ERROR` (nan: False)."""
    t, r = np.nan_to_num(translation_m, nan=0.0), np.nan_to_num(rotation_deg, nan=0.0)
    return (t > GROSS_ERROR[0]) | (r > GROSS_ERROR[1])


@dataclass(frozen=True)
class QueryRun:
    """One configuration of the query-frame protocols (what :func:`perceive_queries` runs).

    ``build_dir``: the build whose query run is perceived against its database run (opened without
    a prior map: no protocol reads the map); ``backbone`` + ``backbone_options``: the
    ``make_backbone`` name and options; ``config``: the pipeline settings (default: the
    pipeline's own; the camera height is calibrated on the first frame, see the module
    docstring); ``n_queries`` evenly spaced frames (0 / None = all); ``seed``: the backbone's noise,
    the Acc / Comp subsampling and the odometry noise; ``mode``: a
    :data:`~vgpnav_env.perception.pipeline.PERCEPTION_MODES` name (:func:`perceive_queries`);
    ``visual_odometry`` (temporal mode): refine the wheel odometry by frame-to-frame visual
    odometry (:mod:`vgpnav_env.perception.odometry`).
    """

    build_dir: Path
    backbone: str = "classical"
    backbone_options: Mapping[str, Any] = field(default_factory=dict)
    config: PerceptionConfig = field(default_factory=PerceptionConfig)
    n_queries: int | None = 50
    seed: int = 0
    mode: str = "paper"
    visual_odometry: bool = True

    def __post_init__(self) -> None:
        from vgpnav_env.perception.pipeline import PERCEPTION_MODES

        if self.mode not in PERCEPTION_MODES:
            raise ValueError(f"unknown perception mode {self.mode!r}; allowed: {', '.join(PERCEPTION_MODES)}")

    @classmethod
    def from_args(
        cls,
        args: argparse.Namespace,
        *,
        scale: bool = True,
        scene: str | None = None,
        build: Path | None = None,
    ) -> QueryRun:
        """The run the arguments of :func:`add_scene_arguments` + :func:`add_pipeline_arguments` ask
        for, on ``scene`` / ``build`` (default ``SCENE`` / ``--build``); bad arguments fail before
        the scene is built."""
        options = backbone_options(args)
        config = config_from_args(args, scale=scale)
        build_dir = resolve_build(args, scene, build)
        mode = getattr(args, "perception_mode", "paper")
        return cls(build_dir, args.backbone, options, config, args.queries, args.seed, mode)

    def feature_choice(self) -> FeatureChoice | None:
        """The classical backbone's scene check on this build's database, once it has been made."""
        from vgpnav_env.perception.backbones import ClassicalConfig

        if self.backbone != "classical":
            return None
        config = self.backbone_options.get("config") or ClassicalConfig(**self.backbone_options)
        return cached_choice(self.build_dir, config) if config.checks_scene else None

    def settings(self) -> dict[str, Any]:
        """The report's settings: build, its scene's perception split (tuning or held-out,
        :func:`~vgpnav_env.tasks.splits.perception_split`), query layout and image size, backbone,
        perception mode, the ablation switches, the query frames and the seed."""
        from vgpnav_env.tasks.splits import perception_split

        meta = read_run_meta(Path(self.build_dir) / "query")
        n = len(query_subset(meta["n_frames"], self.n_queries))
        return {
            "build": str(self.build_dir),
            "perception split": perception_split(str(meta.get("source") or meta.get("scene", ""))),
            "layout": meta["layout"],
            "image size": describe_size(meta["width"], meta["height"]),
            "backbone": self.backbone,
            **(
                {"features": classical_features(self.backbone_options, self.feature_choice())}
                if self.backbone == "classical"
                else {}
            ),
            "perception mode": self.mode,
            "retrieval": self.config.retrieval.method,
            "averaging": self.config.averaging.method,
            "scale_recovery": self.config.scale.enabled,
            "k": self.config.retrieval.k,
            "rerank": self.config.retrieval.rerank,
            "query frames": f"{n} of {meta['n_frames']}",
            "seed": self.seed,
        }


@dataclass(frozen=True)
class QueryFrame:
    """One perceived query frame: its :class:`FrameRecord`, the pipeline's result and the truth it
    was scored against (``T_true`` camera pose, ``surface`` the true visible points in W)."""

    record: FrameRecord
    result: PerceptionResult
    T_true: NDArray[np.float64]
    surface: NDArray[np.float64]


@dataclass(frozen=True)
class QuerySetup:
    """A worker's setup for the query-frame protocols (:mod:`vgpnav_env.eval.workers`): the build,
    its database (no prior: no protocol reads the map) and the backbone, opened once per worker."""

    build_dir: Path
    backbone: str
    backbone_options: Mapping[str, Any]
    seed: int

    def __call__(self) -> QueryWorker:
        build = load_build(self.build_dir)
        db = open_database(build.path, DatabaseConfig(prior="none"))
        net = make_backbone(self.backbone, database=db, seed=self.seed, **self.backbone_options)
        return QueryWorker(build, load_run_depth(build.path / "query"), db, net, self.seed)


@dataclass
class QueryWorker:
    """A worker's state: the build, the query run's true depth, the database and the backbone, and
    a perceiver per pipeline config (built on first use)."""

    build: Build
    depth: NDArray[np.float32]
    database: Database
    backbone: Backbone
    seed: int
    perceivers: dict[PerceptionConfig, Perceiver] = field(default_factory=dict)

    def perceiver(self, config: PerceptionConfig) -> Perceiver:
        if config not in self.perceivers:
            self.perceivers[config] = Perceiver(self.database, self.backbone, config=config)
        return self.perceivers[config]

    def privileged(self, i: int) -> Privileged | None:
        query = self.build.query
        return (
            Privileged(query.poses[i], np.zeros((0, 4, 4)), self.depth[i])
            if self.backbone.privileged
            else None
        )

    def perceive(
        self,
        perceiver: Perceiver,
        i: int,
        max_depth: float,
        max_points: int,
        predicted: NDArray[np.float64] | None = None,
        prior: PoseGate | None = None,
    ) -> QueryFrame:
        """Query frame ``i`` perceived and scored; the backbone's noise and the Acc / Comp
        subsample are seeded by (seed, i), so the frame's result does not depend on the frames
        perceived before it (only on the ground anchor and, temporal mode, the ``predicted`` camera
        pose the references are chosen around and the state estimate's ``prior``)."""
        query, depth = self.build.query, self.depth[i]
        self.backbone.reseed(np.random.default_rng([self.seed, i]))
        result = perceiver.perceive(query.images[i], self.privileged(i), predicted=predicted, prior=prior)
        T = query.poses[i]
        in_range = np.isfinite(depth) & (depth > 0) & (depth <= max_depth)
        surface = query.camera.backproject_world(depth, T, in_range)
        rng = np.random.default_rng([self.seed, i])
        record = _record(i, result, T, surface, rng, max_points, self.database.poses)
        return QueryFrame(record, replace(result, backbone=None), T, surface)


@dataclass(frozen=True)
class _Start:
    """The anchor phase's outcome: the pipeline config with the calibrated camera height, the
    ground anchor and the frames perceived before the anchor was set."""

    config: PerceptionConfig
    anchor: GroundAnchor
    frames: list[QueryFrame]


def _start_task(state: QueryWorker, item: tuple[PerceptionConfig, list[int], float, int]) -> _Start:
    """Initialise the ground anchor on the first frame, the robot standing still, with that frame's
    camera height as the calibrated height; if it does not localize, perceive frames in order
    until one anchors the ground (as a sequential run does) and return them."""
    config, frames, max_depth, max_points = item
    config = replace(config, camera_height=float(state.build.query.poses[frames[0]][2, 3]))
    perceiver = state.perceiver(config)
    perceiver.reset()
    state.backbone.reseed(np.random.default_rng([state.seed, frames[0]]))
    perceiver.initialize(state.build.query.images[frames[0]], state.privileged(frames[0]))
    before = []
    for i in frames:
        if perceiver.initialized:
            break
        before.append(state.perceive(perceiver, i, max_depth, max_points))
    return _Start(config, perceiver.anchor, before)


def _frames_task(state: QueryWorker, item: tuple[_Start, list[int], float, int]) -> list[QueryFrame]:
    """Perceive a contiguous chunk of frames with the anchor phase's config and ground anchor."""
    start, frames, max_depth, max_points = item
    perceiver = state.perceiver(start.config)
    perceiver.reset(start.anchor)
    out = []
    for i in frames:
        note(f"frame {i}")
        out.append(state.perceive(perceiver, i, max_depth, max_points))
    return out


def odometry(
    previous: NDArray[np.float64], pose: NDArray[np.float64], ekf: EKFState, rng: np.random.Generator
) -> NDArray[np.float64]:
    """Simulated wheel odometry from the planar pose ``previous`` to ``pose`` (x, y, yaw): the true
    motion (forward m, left m, yaw rad) in the robot frame of ``previous`` plus Gaussian noise of
    the covariance ``ekf`` models (:meth:`EKFState.odometry_covariance`)."""
    c, s = np.cos(previous[2]), np.sin(previous[2])
    dx, dy = pose[:2] - previous[:2]
    motion = np.array([c * dx + s * dy, -s * dx + c * dy, wrap_angle(pose[2] - previous[2])])
    sigma = np.sqrt(np.diag(ekf.odometry_covariance(motion)))
    return motion + rng.normal(0.0, 1.0, 3) * sigma


def _temporal_task(
    state: QueryWorker, item: tuple[PerceptionConfig, list[int], float, int, bool]
) -> list[QueryFrame]:
    """Temporal mode: every frame in order, an :class:`EKFState` carried along by simulated wheel
    odometry (:func:`odometry`, seeded by (seed, frame); refined by visual odometry when asked,
    :func:`~vgpnav_env.perception.odometry.fuse_motion`); while it is certain the perceiver tracks
    (references around the predicted camera), its :meth:`~EKFState.prior` goes to the perceiver,
    and it takes in the perceived poses
    (:attr:`~vgpnav_env.perception.pipeline.PerceptionResult.measurement`) with their verifier
    confidence, as the env's wrapper does (one fix scoring ``EKFConfig.init_score`` starts the first
    estimate alone, instead of waiting for a second fix from another view). The ground is anchored
    on the first frame standing still, as in paper mode. The frames it then trusts become sweep
    references of the frames after them (:attr:`~vgpnav_env.perception.pipeline.Perceiver.recent`),
    as the wrapper's mapped frames do. A record's ``cpu`` timing includes the odometry's
    (``odometry_cpu``)."""
    config, frames, max_depth, max_points, visual_odometry = item
    query = state.build.query
    T0 = query.poses[frames[0]]
    height, pitch = float(T0[2, 3]), camera_yaw_pitch(T0)[1]
    perceiver = state.perceiver(replace(config, camera_height=height))
    perceiver.reset()
    state.backbone.reseed(np.random.default_rng([state.seed, frames[0]]))
    perceiver.initialize(query.images[frames[0]], state.privileged(frames[0]))
    truth = np.array([base_pose(query.poses[i]) for i in frames])
    margin = np.array([5.0, 5.0, 0.0])
    low = np.append(truth[:, :2].min(0), -np.pi) - margin
    high = np.append(truth[:, :2].max(0), np.pi) + margin
    ekf = EKFState(low, high)
    ekf.reset(query.images[frames[0]], fallback=(0.5 * (low + high))[:2].tolist() + [0.0])
    vo = VisualOdometry(perceiver.camera, height, pitch) if visual_odometry else None
    if vo is not None:
        vo.reset(query.images[frames[0]])
    out = []
    for n, i in enumerate(frames):
        note(f"frame {i}")
        used, vo_cpu = False, time.process_time()
        if n:
            rng = np.random.default_rng([state.seed, i, 1])
            motion = odometry(truth[n - 1], truth[n], ekf, rng)
            visual = vo.measure(query.images[i]) if vo is not None else None
            motion, covariance, used = fuse_motion(motion, ekf.odometry_covariance(motion), visual)
            ekf.predict_odometry(motion, covariance)
        vo_cpu = time.process_time() - vo_cpu
        predicted = ekf.tracking_pose()
        T_pred = None if predicted is None else camera_T_wc(predicted, height, pitch)
        frame = state.perceive(perceiver, i, max_depth, max_points, predicted=T_pred, prior=ekf.prior())
        measured = frame.result.measurement
        ekf.correct(None if measured is None else base_pose(measured), frame.result.confidence)
        if ekf.localized and frame.result.localized and not frame.result.prior_placed:
            perceiver.recent.add(query.images[i], frame.result.T_wc)  # a trusted frame: a sweep reference
        error = float(np.linalg.norm(ekf.estimate[:2] - truth[n, :2])) if ekf.has_estimate else float("nan")
        timings = frame.record.timings | {"cpu": frame.record.timings["cpu"] + vo_cpu, "odometry_cpu": vo_cpu}
        record = replace(
            frame.record, fix=ekf.fix, estimate_error_m=error, visual_odometry=used, timings=timings
        )
        out.append(replace(frame, record=record))
    return out


def perceive_queries(
    run: QueryRun,
    *,
    workers: Workers | None = None,
    max_depth: float = 5.0,
    max_points: int = 4000,
    progress: bool = True,
) -> list[QueryFrame]:
    """Every query frame of ``run`` perceived and scored (module docstring), in frame order.

    ``workers`` (default: this process) run the frames. Temporal mode (``run.mode``): one task
    perceives them in order with the state estimate (:func:`_temporal_task`). Paper mode: a query
    run is a sequence and its ground anchor is state carried along it, so the work is split in two
    phases that give the same frames whatever the number of workers: (1) one task initialises the
    anchor on the first frame standing still, perceiving further frames in order only while none
    has anchored the ground; (2) the remaining frames go out in contiguous chunks, each perceived
    by a fresh map with a copy of that anchor. Nothing else carries over between frames: the
    pipeline's results do not read the fused map, and each frame's random draws are seeded by
    (seed, frame). The results carry the pipeline's output without the backbone's raw output
    (``result.backbone`` None).
    """
    own = workers is None
    workers = workers or Workers(1, progress=progress)
    try:
        if workers.workers > 1 or workers.ray_address is not None:
            # Prepare the database's cached index and features once, before the workers open it.
            open_database(run.build_dir, DatabaseConfig(prior="none"))
        n_frames = read_run_meta(Path(run.build_dir) / "query")["n_frames"]
        frames = [int(i) for i in query_subset(n_frames, run.n_queries)]
        setup = QuerySetup(Path(run.build_dir), run.backbone, dict(run.backbone_options), run.seed)
        first = (run.config, frames, max_depth, max_points)
        if run.mode == "temporal":  # one sequence, one task: the state is carried frame to frame
            task = (*first, run.visual_odometry)
            (done,) = workers.map(setup, _temporal_task, [task], desc="perceiving queries in order")
            return done
        (start,) = workers.map(setup, _start_task, [first], desc="ground anchor")
        rest = frames[len(start.frames) :]
        size = 1 if workers.workers == 1 else max(1, -(-len(rest) // (4 * workers.workers)))
        chunks = [(start, rest[k : k + size], max_depth, max_points) for k in range(0, len(rest), size)]
        done = workers.map(setup, _frames_task, chunks, desc="perceiving queries")
    finally:
        if own:
            workers.close()
    return [*start.frames, *(frame for chunk in done for frame in chunk)]


def query_records(run: QueryRun, **kwargs: Any) -> list[FrameRecord]:
    """The :class:`FrameRecord` of every frame of :func:`perceive_queries` (same arguments)."""
    return [frame.record for frame in perceive_queries(run, **kwargs)]


def pose_errors(T_est: NDArray[np.float64] | None, T_true: NDArray[np.float64]) -> tuple[float, float]:
    """(translation metres, rotation degrees) of ``T_est`` against ``T_true`` (nan when None)."""
    if T_est is None:
        return float("nan"), float("nan")
    dt = float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))
    return dt, float(np.degrees(rotation_angle(T_est[:3, :3], T_true[:3, :3])))


def retrieval_hit(refs: NDArray[np.int64], T_w: NDArray[np.float64], T_true: NDArray[np.float64]) -> bool:
    """Whether a database camera ``T_w[refs]`` lies within :data:`RETRIEVAL_HIT` of ``T_true``."""
    if len(refs) == 0:
        return False
    return len(nearby_cameras(T_w[refs], T_true, *RETRIEVAL_HIT).index) > 0


def _record(
    i: int,
    result: PerceptionResult,
    T: NDArray[np.float64],
    gt: NDArray[np.float64],
    rng,
    max_points: int,
    T_w: NDArray[np.float64],
) -> FrameRecord:
    nan = float("nan")
    candidate = pose_errors(result.T_wc, T)
    if result.localized:
        dt, dr = candidate
        acc, comp = accuracy_completeness(result.points_w.astype(np.float64), gt, rng, max_points)
    else:
        dt = dr = acc = comp = nan
    return FrameRecord(
        frame=i,
        status=result.status,
        reason=result.reason,
        translation_m=dt,
        rotation_deg=dr,
        acc_m=acc,
        comp_m=comp,
        scale_source=result.scale_source,
        n_references=len(result.references),
        n_confident_pairs=result.n_confident_pairs,
        n_points=len(result.points_w),
        timings=dict(result.timings),
        detail=result.detail,
        candidate_translation_m=candidate[0],
        candidate_rotation_deg=candidate[1],
        retrieval_hit=retrieval_hit(result.retrieved, T_w, T),
        source=result.source,
        retrieved=[int(j) for j in result.retrieved],
        references=[int(j) for j in result.references],
        confidence=result.confidence,
        candidate_confidence=result.verdict.trust if result.verdict is not None else float("nan"),
        gate=_gate(result),
        prior_placed=result.prior_placed,
        evidence=_evidence(result),
    )


def _evidence(result: PerceptionResult) -> dict[str, float]:
    """:attr:`FrameRecord.evidence`: the verdict's evidence as numbers ({} without one)."""
    verdict = result.verdict
    if verdict is None or verdict.evidence is None:
        return {}
    return {k: float(v) for k, v in asdict(verdict.evidence).items()}


def _gate(result: PerceptionResult) -> str:
    """:attr:`FrameRecord.gate` of a result."""
    if result.localized:
        return ""
    verdict = result.verdict
    if result.reason == "unverified" and verdict is not None and verdict.check:
        return f"unverified: {verdict.check}"
    return result.reason


def _stats(values: NDArray[np.float64]) -> tuple[float, float]:
    """(median, mean) of the finite values (nan, nan when none)."""
    v = values[np.isfinite(values)]
    return (float(np.median(v)), float(np.mean(v))) if len(v) else (float("nan"), float("nan"))


def confidence_roc(records: list[FrameRecord]) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """ROC of the verification's confidence as a test of "this pose is right" (false- and
    true-positive rates (n,), AUC; nan when a class is empty): over the frames whose pose was
    verified (accepted or not), right = not a gross error (:data:`GROSS_ERROR`), wrong = gross,
    scored by ``candidate_confidence``."""
    scored = [r for r in records if np.isfinite(r.candidate_confidence)]
    score = np.array([r.candidate_confidence for r in scored], float)
    wrong = np.array([is_gross(r.candidate_translation_m, r.candidate_rotation_deg) for r in scored], bool)
    n_right, n_wrong = int((~wrong).sum()), int(wrong.sum())
    if n_right == 0 or n_wrong == 0:
        return np.zeros(0), np.zeros(0), float("nan")
    thresholds = np.r_[np.inf, np.unique(score)[::-1]]
    tpr = np.array([(score[~wrong] >= t).mean() for t in thresholds])
    fpr = np.array([(score[wrong] >= t).mean() for t in thresholds])
    right, bad = score[~wrong][:, None], score[wrong][None, :]
    auc = float(((right > bad).sum() + 0.5 * (right == bad).sum()) / (n_right * n_wrong))
    return fpr, tpr, auc


#: How far a lost frame's rejected pose was from the truth: class -> meaning (:func:`candidate_class`).
CANDIDATE_CLASSES = {
    "right": "within 5 cm and 5 deg",
    "near": "within 0.5 m and 10 deg (not right)",
    "wrong": "more than 0.5 m or 10 deg off",
    "no pose": "no pose was estimated",
}


def candidate_class(translation_m: float, rotation_deg: float) -> str:
    """The :data:`CANDIDATE_CLASSES` name of a pose error (metres, degrees; nan: no pose)."""
    if not (np.isfinite(translation_m) and np.isfinite(rotation_deg)):
        return "no pose"
    if is_gross(translation_m, rotation_deg):
        return "wrong"
    tm, deg = RECALL_THRESHOLDS["recall_5cm_5deg"]
    return "right" if translation_m <= tm and rotation_deg <= deg else "near"


def localization_metrics(records: list[FrameRecord]) -> dict[str, Any]:
    """Localization metrics of a query run (DESIGN.md "Metrics").

    Over all queries (a lost query is a failure): the recalls of :data:`RECALL_THRESHOLDS`,
    ``lost_rate``, ``lost_by_reason`` and ``retrieval_recall``. Over localized queries: median
    and mean translation / rotation errors, ``n_gross`` and ``gross_rate`` (:data:`GROSS_ERROR`).
    ``confidence_auc``: :func:`confidence_roc`; ``n_rejected_right``: lost frames whose rejected
    pose was right (within 0.25 m and 2 deg), the price of the verification. ``lost_by_gate``:
    lost frames per :attr:`FrameRecord.gate`, split by their rejected pose (:data:`CANDIDATE_CLASSES`).
    """
    n = len(records)
    t = np.array([r.translation_m for r in records], float)
    rdeg = np.array([r.rotation_deg for r in records], float)
    ok = np.array([r.status == "localized" for r in records], bool)
    lost_by_reason: dict[str, int] = {}
    lost_by_gate: dict[str, dict[str, int]] = {}
    for r in records:
        if r.status != "localized":
            lost_by_reason[r.reason] = lost_by_reason.get(r.reason, 0) + 1
            gate = lost_by_gate.setdefault(r.gate or r.reason, dict.fromkeys(CANDIDATE_CLASSES, 0))
            gate[candidate_class(r.candidate_translation_m, r.candidate_rotation_deg)] += 1
    median_t, mean_t = _stats(t[ok])
    median_r, mean_r = _stats(rdeg[ok])
    n_gross = int(is_gross(t[ok], rdeg[ok]).sum())
    out: dict[str, Any] = {
        "n_queries": n,
        "n_localized": int(ok.sum()),
        "n_lost": int(n - ok.sum()),
        "lost_rate": float((n - ok.sum()) / n) if n else float("nan"),
        "lost_by_reason": dict(sorted(lost_by_reason.items())),
        "lost_by_gate": dict(sorted(lost_by_gate.items())),
        "n_gross": n_gross,
        "gross_rate": float(n_gross / ok.sum()) if ok.any() else float("nan"),
        "median_translation_m": median_t,
        "mean_translation_m": mean_t,
        "median_rotation_deg": median_r,
        "mean_rotation_deg": mean_r,
        "retrieval_recall": float(np.mean([r.retrieval_hit for r in records])) if n else float("nan"),
        "confidence_auc": confidence_roc(records)[2],
        "n_rejected_right": sum(
            r.status != "localized" and r.candidate_translation_m <= 0.25 and r.candidate_rotation_deg <= 2.0
            for r in records
        ),
    }
    for key, (tm, deg) in RECALL_THRESHOLDS.items():
        hit = ok & (np.nan_to_num(t, nan=np.inf) <= tm) & (np.nan_to_num(rdeg, nan=np.inf) <= deg)
        out[key] = float(hit.mean()) if n else float("nan")
    return out


def temporal_metrics(records: list[FrameRecord]) -> dict[str, Any]:
    """The state estimate's metrics of a temporal-mode run (empty for paper mode): ``fixes`` (count
    per :data:`~vgpnav_env.perception.state.FIX_OUTCOMES` name), ``tracked_rate`` (frames whose
    references came from tracking), ``no_estimate_rate`` (frames before the first estimate) and,
    over the frames with an estimate, its horizontal error: ``estimate_mean_m``,
    ``estimate_median_m``, ``estimate_p95_m`` and ``estimate_gross_rate`` (more than
    :data:`~vgpnav_env.measures.GROSS_POSE_ERROR_M` off); ``n_prior_placed`` / ``prior_placed_rate``:
    the frames localized only thanks to the estimate's prior (:attr:`FrameRecord.prior_placed`)."""
    from vgpnav_env.measures import GROSS_POSE_ERROR_M

    if not records or not records[0].fix:
        return {}
    errors = np.array([r.estimate_error_m for r in records], float)
    have = np.isfinite(errors)
    fixes: dict[str, int] = {}
    for r in records:
        fixes[r.fix] = fixes.get(r.fix, 0) + 1
    e = errors[have]
    return {
        "fixes": dict(sorted(fixes.items())),
        "n_prior_placed": sum(r.prior_placed for r in records),
        "prior_placed_rate": float(np.mean([r.prior_placed for r in records])),
        "tracked_rate": float(np.mean([r.source == "tracking" for r in records])),
        "visual_odometry_rate": float(np.mean([r.visual_odometry for r in records])),
        "no_estimate_rate": float(1.0 - have.mean()),
        "estimate_mean_m": float(e.mean()) if len(e) else float("nan"),
        "estimate_median_m": float(np.median(e)) if len(e) else float("nan"),
        "estimate_p95_m": float(np.percentile(e, 95)) if len(e) else float("nan"),
        "estimate_gross_rate": float((e > GROSS_POSE_ERROR_M).mean()) if len(e) else float("nan"),
    }


def perception_metrics(records: list[FrameRecord]) -> dict[str, Any]:
    """Acc / Comp / Overall (metres): mean (``acc_m``, ...) and median (``acc_median_m``, ...) over
    the localized frames with points (``n_frames``); Overall per frame = (Acc + Comp) / 2. Lost
    frames have no points and are counted apart (``n_lost``, ``lost_rate`` of all queries)."""
    acc = np.array([r.acc_m for r in records], float)
    comp = np.array([r.comp_m for r in records], float)
    ok = np.isfinite(acc) & np.isfinite(comp)
    out: dict[str, Any] = {}
    for name, values in (("acc", acc), ("comp", comp), ("overall", 0.5 * (acc + comp))):
        median, mean = _stats(values[ok])
        out |= {f"{name}_m": mean, f"{name}_median_m": median}
    n_lost = sum(r.status != "localized" for r in records)
    return out | {
        "n_frames": int(ok.sum()),
        "n_queries": len(records),
        "n_lost": n_lost,
        "lost_rate": n_lost / len(records) if records else float("nan"),
    }


def config_from_args(args: argparse.Namespace, *, scale: bool = True) -> PerceptionConfig:
    if args.k < 1:
        raise ValueError(f"--k must be >= 1, got {args.k}")
    config = PerceptionConfig.ablation(
        retrieval=args.retrieval, averaging=args.averaging, scale=scale, k=args.k, rerank=args.rerank
    )
    verification = getattr(args, "verification", "rules")
    return replace(config, verify=replace(config.verify, decision=verification))
