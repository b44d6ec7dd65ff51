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
from vgpnav_env.perception.model import PerceptionModel, fit_model, median_depth
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
    return fit_model(records, medians, sampled, source=info)


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
    return 0
