"""Running VGP-Nav perception over a build's query run and scoring every frame.

Shared by the localization, perception, timing and ablation protocols:

- :func:`add_scene_arguments` / :func:`resolve_build`: ``SCENE`` + ``--build DIR`` (else the scene
  is built, or reused, with :func:`vgpnav_env.build.build_runs` in the default cache directory);
- :func:`evaluate_queries`: one :class:`~vgpnav_env.perception.pipeline.Perceiver` over an evenly
  spaced subset of the query run. The ground anchor is initialised on the first query frame (the
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
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from tqdm import tqdm

from vgpnav_env.geometry import rotation_angle
from vgpnav_env.perception.backbones import Privileged, make_backbone
from vgpnav_env.perception.database import Database, DatabaseConfig
from vgpnav_env.perception.pipeline import Perceiver, PerceptionConfig, PerceptionResult
from vgpnav_env.robot import CAMERA_HEIGHT
from vgpnav_env.runs import Build, load_build, load_run_depth

logger = logging.getLogger(__name__)

#: Nominal camera-to-base height of the query runs (metres), the calibrated anchor.
QUERY_CAMERA_HEIGHT = CAMERA_HEIGHT
BACKBONE_CHOICES = ("classical", "simulated")
#: (translation metres, rotation degrees) thresholds of the recall metrics.
RECALL_THRESHOLDS = {
    "recall_5cm_5deg": (0.05, 5.0),
    "recall_10cm_10deg": (0.10, 10.0),
    "recall_25cm_2deg": (0.25, 2.0),
}


def add_scene_arguments(parser: argparse.ArgumentParser, *, queries: int | None = 50) -> None:
    """``SCENE``, ``--build``, ``--size``, ``--seed``, ``--texture``, ``--out``, ``--queries``."""
    from vgpnav_env.cli import seed_arg, size_arg

    parser.add_argument("scene", help="built-in scene name or a scene spec file (ignored with --build)")
    parser.add_argument(
        "--build", type=Path, help="an existing build directory (default: build or reuse one)"
    )
    parser.add_argument(
        "--size", type=size_arg, default=(320, 240), metavar="WxH", help="image size (default 320x240)"
    )
    parser.add_argument("--seed", type=seed_arg, default=0, help="trajectory seed of the build (default 0)")
    parser.add_argument(
        "--texture", default="realistic", help="texture level of the build (default realistic)"
    )
    parser.add_argument("--out", type=Path, required=True, help="report directory")
    parser.add_argument(
        "--queries",
        type=int,
        default=queries,
        help=f"number of evenly spaced query frames, 0 = all (default {queries or 'all'})",
    )


def add_pipeline_arguments(parser: argparse.ArgumentParser, *, backbone: bool = True) -> None:
    """``--backbone``, ``--retrieval``, ``--averaging``, ``--k``, ``--prior``."""
    if backbone:
        parser.add_argument(
            "--backbone", choices=BACKBONE_CHOICES, default="classical", help="default classical"
        )
    parser.add_argument(
        "--retrieval", choices=("geometry", "topk"), default="geometry", help="default geometry"
    )
    parser.add_argument(
        "--averaging", choices=("weighted", "single"), default="weighted", help="default weighted"
    )
    parser.add_argument("--k", type=int, default=10, help="number of references (default 10)")
    parser.add_argument(
        "--prior",
        choices=("database", "none"),
        default="none",
        help="start the map from the database prior (built once, minutes) or empty (default none)",
    )


def resolve_build(args: argparse.Namespace) -> Path:
    """The build directory: ``--build`` or the (possibly new) default build of ``SCENE``."""
    if args.build is not None:
        return Path(args.build)
    from vgpnav_env.build import build_runs, default_build_dir

    out = default_build_dir(args.scene, tuple(args.size), args.seed, args.texture)
    build_runs(args.scene, out, size=tuple(args.size), seed=args.seed, texture=args.texture, progress=False)
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
    """One query frame's outcome (errors nan when lost)."""

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


@dataclass
class QueryEvaluation:
    """Records of every evaluated frame plus one example frame's points (for figures)."""

    records: list[FrameRecord]
    example: dict[str, Any] = field(default_factory=dict)


def open_database(build: Build | Path, prior: str = "none") -> Database:
    path = build.path if isinstance(build, Build) else Path(build)
    return Database.open(path, config=DatabaseConfig(prior=prior))


def evaluate_queries(
    build_dir: Path,
    *,
    backbone: str = "classical",
    config: PerceptionConfig | None = None,
    n_queries: int | None = 50,
    prior: str = "none",
    seed: int = 0,
    max_depth: float = 5.0,
    max_points: int = 4000,
    database: Database | None = None,
    progress: bool = True,
) -> QueryEvaluation:
    """Perceive an evenly spaced subset of the query run and score every frame (module docstring)."""
    if backbone not in BACKBONE_CHOICES:
        raise ValueError(f"backbone must be one of {BACKBONE_CHOICES}, got {backbone!r}")
    build = load_build(build_dir)
    config = config or PerceptionConfig(camera_height=QUERY_CAMERA_HEIGHT)
    db = database or open_database(build, prior)
    query = build.query
    depth = load_run_depth(build.path / "query")
    net = (
        make_backbone(backbone, seed=seed)
        if backbone == "simulated"
        else make_backbone(backbone, feature_cache=db.feature_cache)
    )
    frames = query_subset(len(query), n_queries)
    # Calibrated camera-to-base height of the standing-still frame (floor at z = 0 in W).
    config = replace(config, camera_height=float(query.poses[frames[0]][2, 3]))
    perceiver = Perceiver(db, net, config=config)

    def privileged(i: int) -> Privileged | None:
        return Privileged(query.poses[i], np.zeros((0, 4, 4)), depth[i]) if backbone == "simulated" else None

    perceiver.initialize(query.images[frames[0]], privileged(frames[0]))
    rng = np.random.default_rng(seed)
    cam = query.camera
    records: list[FrameRecord] = []
    example: dict[str, Any] = {}
    for i in tqdm(frames, desc="perceiving queries", unit="frame", disable=not progress):
        result = perceiver.perceive(query.images[i], privileged(i))
        T = query.poses[i]
        in_range = np.isfinite(depth[i]) & (depth[i] > 0) & (depth[i] <= max_depth)
        gt = cam.backproject_world(depth[i], T, in_range)
        records.append(_record(int(i), result, T, gt, rng, max_points))
        if result.localized and (not example or records[-1].n_points > example["n_points"]):
            example = {
                "frame": int(i),
                "pred": result.points_w,
                "gt": gt,
                "T_true": T,
                "T_est": result.T_wc,
                "n_points": records[-1].n_points,
            }
    return QueryEvaluation(records, example)


def _record(
    i: int, result: PerceptionResult, T: NDArray[np.float64], gt: NDArray[np.float64], rng, max_points: int
) -> FrameRecord:
    nan = float("nan")
    if result.localized:
        dt = float(np.linalg.norm(result.T_wc[:3, 3] - T[:3, 3]))
        dr = float(np.degrees(rotation_angle(result.T_wc[:3, :3], T[:3, :3])))
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
        timings=dict(result.timings)
        | {f"backbone.{k}": v for k, v in (result.backbone.timings if result.backbone else {}).items()},
    )


def localization_metrics(records: list[FrameRecord]) -> dict[str, Any]:
    """Median errors over localized frames; recalls over all frames (lost = failure)."""
    t = np.array([r.translation_m for r in records], float)
    rdeg = np.array([r.rotation_deg for r in records], float)
    ok = np.isfinite(t)
    out: dict[str, Any] = {
        "median_translation_m": float(np.median(t[ok])) if ok.any() else float("nan"),
        "median_rotation_deg": float(np.median(rdeg[ok])) if ok.any() else float("nan"),
        "n_queries": len(records),
        "n_lost": int((~ok).sum()),
    }
    for key, (tm, deg) in RECALL_THRESHOLDS.items():
        hit = ok & (np.nan_to_num(t, nan=np.inf) <= tm) & (np.nan_to_num(rdeg, nan=np.inf) <= deg)
        out[key] = float(hit.mean()) if len(records) else float("nan")
    return out


def perception_metrics(records: list[FrameRecord]) -> dict[str, Any]:
    """Acc / Comp / Overall averaged over frames with points; lost frames are counted apart."""
    acc = np.array([r.acc_m for r in records], float)
    comp = np.array([r.comp_m for r in records], float)
    ok = np.isfinite(acc) & np.isfinite(comp)
    a = float(acc[ok].mean()) if ok.any() else float("nan")
    c = float(comp[ok].mean()) if ok.any() else float("nan")
    return {
        "acc_m": a,
        "comp_m": c,
        "overall_m": 0.5 * (a + c),
        "n_frames": int(ok.sum()),
        "n_queries": len(records),
        "n_lost": sum(r.status == "lost" for r in records),
    }


def config_from_args(args: argparse.Namespace, *, scale: bool = True) -> PerceptionConfig:
    if args.k < 1:
        raise ValueError(f"--k must be >= 1, got {args.k}")
    return PerceptionConfig.ablation(
        retrieval=args.retrieval,
        averaging=args.averaging,
        scale=scale,
        k=args.k,
        camera_height=QUERY_CAMERA_HEIGHT,
    )
