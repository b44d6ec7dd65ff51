"""Metric perception protocol: Acc / Comp / Overall of VGP-Nav's metric points (paper Table III).

``vgpnav eval perception SCENE --backbone B [--no-scale-recovery] [--retrieval geometry|topk]
[--averaging weighted|single] [--k 10] [--queries N] --out DIR [--build DIR]``

Per query frame the predicted metric world points (confident pixels) are compared with the true
visible surface of that frame (see :mod:`vgpnav_env.eval.perception_runs`): Acc = mean
nearest-neighbour distance predicted -> true, Comp = true -> predicted, averaged over the frames
that localized; Overall = their mean. The ground anchor is initialised on the first query frame
with that frame's camera height as the calibrated height and kept for the run. Writes ``DIR/report.json``
(``acc_m``, ``comp_m``, ``overall_m``, ``n_frames``, ``n_lost``, records) and ``DIR/report.md``
with a top-down figure of predicted vs true points of one frame (``points.png``).
"""

from __future__ import annotations

import argparse
from dataclasses import asdict
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from vgpnav_env.eval.perception_runs import (
    FrameRecord,
    QueryFrame,
    QueryRun,
    add_pipeline_arguments,
    add_scene_arguments,
    perceive_queries,
    perception_metrics,
)
from vgpnav_env.eval.report import markdown_table, write_report

#: Paper Table III (Acc, Comp, Overall in metres) for comparison.
PAPER = {
    "VGP-Nav Home": (0.08, 0.03, 0.05),
    "VGP-Nav Hospital": (0.10, 0.08, 0.09),
    "MoGe-2 Home": (0.18, 0.15, 0.16),
    "MapAnything Home": (0.10, 0.07, 0.08),
}


def points_figure(example: QueryFrame | None, max_points: int = 6000, seed: int = 0) -> Figure:
    """Top-down (x, y) view of one frame's predicted (orange) and true (blue) points with both cameras."""
    fig = Figure(figsize=(5.5, 5.0))
    ax = fig.subplots()
    rng = np.random.default_rng(seed)
    if example is not None:
        for p, colour, label in (
            (example.surface, "tab:blue", "true surface"),
            (example.result.points_w, "tab:orange", "predicted"),
        ):
            if len(p) > max_points:
                p = p[rng.choice(len(p), max_points, replace=False)]
            ax.scatter(p[:, 0], p[:, 1], s=1, c=colour, alpha=0.5, label=label)
        for T, marker, label in (
            (example.T_true, "o", "true camera"),
            (example.result.T_wc, "x", "estimated camera"),
        ):
            ax.plot(*T[:2, 3], marker, c="k", label=label)
            ax.arrow(*T[:2, 3], *(0.4 * T[:2, 2]), head_width=0.05, color="k")
        ax.set_title(f"query frame {example.record.frame} (top-down, metres)")
        ax.legend(loc="best", fontsize=7, markerscale=4)
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    return fig


def evaluate_perception(run: QueryRun, *, progress: bool = True) -> tuple[dict[str, Any], QueryFrame | None]:
    """(metrics dict, the localized frame with the most points for :func:`points_figure`)."""
    records: list[FrameRecord] = []
    example: QueryFrame | None = None
    for frame in perceive_queries(run, progress=progress):
        records.append(frame.record)
        if frame.result.localized and (example is None or frame.record.n_points > example.record.n_points):
            example = frame
    return {**perception_metrics(records), "records": [asdict(r) for r in records]}, example


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_scene_arguments(parser, queries=50)
    add_pipeline_arguments(parser)
    parser.add_argument(
        "--no-scale-recovery",
        action="store_true",
        help="ablation: keep the backbone's unknown scale (no ground-anchored scale recovery)",
    )


def run(args: argparse.Namespace) -> int:
    query_run = QueryRun.from_args(args, scale=not args.no_scale_recovery)
    metrics, example = evaluate_perception(query_run)
    settings = {"scene": args.scene, **query_run.settings()}
    sections = [
        "## Settings\n\n" + markdown_table(["setting", "value"], list(settings.items())),
        "## Paper Table III (m)\n\n"
        + markdown_table(["method", "Acc", "Comp", "Overall"], [(k, *v) for k, v in PAPER.items()], ".2f"),
        "Acc / Comp are averaged over the frames that localized (n_frames); points farther than 5 m "
        "from the camera are left out of both sets.",
    ]
    figures = {"points.png": points_figure(example, seed=args.seed)}
    write_report(args.out, "Metric perception", {**metrics, "settings": settings}, sections, figures)
    return 0
