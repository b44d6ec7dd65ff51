"""``vgpnav calibrate SCENE --backbone classical --out FILE.json``: fit the ``model`` perception.

Runs the localization protocol on the scene's query run (as ``vgpnav eval localization``; or reads
an existing report with ``--from-report``), takes the median ground-truth depth of every query view
and fits a :class:`~vgpnav_env.perception.model.PerceptionModel` (lost probability against the
view's median depth, its stickiness, pose errors with the gross ones, depth noise and coverage).
Prints the fitted statistics beside the measured ones.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from vgpnav_env.eval.perception_runs import (
    QueryRun,
    add_pipeline_arguments,
    add_scene_arguments,
    query_records,
)
from vgpnav_env.eval.workers import add_worker_arguments, workers_from_args
from vgpnav_env.perception.model import (
    PerceptionModel,
    PriorErrors,
    base_cells,
    fit_model,
    fit_prior_errors,
    median_depth,
)
from vgpnav_env.perception.occupancy import OccupancyConfig
from vgpnav_env.runs import load_run_depth, read_run_meta


def calibrate(
    build_dir: str | Path, records: list[dict[str, Any]], source: dict[str, Any] | None = None
) -> PerceptionModel:
    """Fit the model to localization ``records`` of the query run of ``build_dir``."""
    query = Path(build_dir) / "query"
    meta = read_run_meta(query)
    depth = load_run_depth(query)
    medians = [median_depth(depth[r["frame"]]) for r in records]
    stride = OccupancyConfig().point_stride
    sampled = -(-meta["width"] // stride) * -(-meta["height"] // stride)
    info = {"build": str(build_dir), "image size": f"{meta['width']}x{meta['height']}", **(source or {})}
    return replace(
        fit_model(records, medians, sampled, source=info), prior_errors=database_prior_errors(build_dir)
    )


def database_prior_errors(build_dir: str | Path) -> PriorErrors | None:
    """:class:`PriorErrors` of the prior map of ``build_dir``'s database (computed and cached on
    first use) against the ground truth of the base layout; None without a prior."""
    from vgpnav_env.perception.database import open_database
    from vgpnav_env.robot import ROBOT_HEIGHT, ROBOT_RADIUS

    prior = open_database(build_dir).prior
    if prior is None:
        return None
    scene = read_run_meta(Path(build_dir) / "database")["scene"]
    free, obstacle = base_cells(scene, prior.spec, ROBOT_RADIUS, ROBOT_HEIGHT)
    return fit_prior_errors(prior.probability(), free, obstacle, prior.spec.resolution)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_scene_arguments(parser, queries=0)
    add_pipeline_arguments(parser)
    add_worker_arguments(parser)
    parser.add_argument(
        "--from-report",
        type=Path,
        default=None,
        help="fit from an existing 'vgpnav eval localization' report.json of the same build",
    )


def run(args: argparse.Namespace) -> int:
    if args.out.suffix != ".json":
        raise ValueError(f"--out must be a .json file, got {args.out}")
    if args.from_report is not None and not args.from_report.is_file():
        raise ValueError(f"--from-report {args.from_report}: no such file")
    query_run = QueryRun.from_args(args)
    source = {"scene": args.scene, "backbone": args.backbone, "queries": args.queries}
    if args.from_report is not None:
        report = json.loads(args.from_report.read_text())
        records = report["records"]
        source["report"] = str(args.from_report)
    else:
        from dataclasses import asdict

        with workers_from_args(args) as workers:
            records = [asdict(r) for r in query_records(query_run, workers=workers)]
    model = calibrate(query_run.build_dir, records, source)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    model.save(args.out)
    lost = np.mean([r["status"] != "localized" for r in records])
    print(f"calibrated on {len(records)} query frames of {args.scene} ({args.backbone}) -> {args.out}")
    print(
        f"  lost rate {lost:.3f}; lost probability per median-depth bin {np.round(model.p_lost, 3).tolist()}"
    )
    print(
        f"  depth bin edges (m) {np.round(model.depth_edges, 2).tolist()}; stickiness {model.stickiness:.2f}"
    )
    print(
        f"  gross rate {model.p_gross:.3f} ({len(model.gross_translation_m)} gross); inlier median "
        f"{np.exp(model.log_translation[0]):.4f} m / {np.exp(model.log_rotation[0]):.3f} deg"
    )
    print(f"  depth noise {model.depth_noise_m:.3f} m, coverage {model.coverage:.2f}")
    if model.prior_errors is not None:
        e = model.prior_errors
        print(
            f"  database prior: free cells occupied {np.round(e.free_occupied, 3).tolist()} / unknown "
            f"{np.round(e.free_unknown, 3).tolist()} by distance to an obstacle (edges {e.free_edges} m); "
            f"obstacle cells occupied {np.round(e.obstacle_occupied, 3).tolist()} / unknown "
            f"{np.round(e.obstacle_unknown, 3).tolist()} by distance to free space"
        )
    return 0
