"""Localization protocol: median pose error and recall of VGP-Nav on a scene's query run.

``vgpnav eval localization SCENE --backbone B [--queries N] [--retrieval geometry|topk]
[--averaging weighted|single] [--k 10] --out DIR [--size WxH] [--seed S] [--build DIR]``

Writes ``DIR/report.json`` with ``median_translation_m`` / ``median_rotation_deg`` (over the
localized queries), ``recall_5cm_5deg``, ``recall_10cm_10deg``, ``recall_25cm_2deg`` (over all
queries; a lost query is a failure), ``n_queries``, ``n_lost``, the settings and one record per
query; ``DIR/report.md`` with the error CDFs (``errors.png``).
"""

from __future__ import annotations

import argparse
import logging
from dataclasses import asdict
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from vgpnav_env.eval.perception_runs import (
    FrameRecord,
    QueryRun,
    add_pipeline_arguments,
    add_scene_arguments,
    localization_metrics,
    query_records,
)
from vgpnav_env.eval.report import markdown_table, write_report

logger = logging.getLogger(__name__)


def error_cdf_figure(records: list[FrameRecord], title: str = "") -> Figure:
    """Cumulative fraction of ALL queries (lost never reach 1) below a translation / rotation error."""
    fig = Figure(figsize=(9, 3.4))
    axes = fig.subplots(1, 2)
    n = max(len(records), 1)
    for ax, key, unit, marks in (
        (axes[0], "translation_m", "m", (0.05, 0.10, 0.25)),
        (axes[1], "rotation_deg", "deg", (2.0, 5.0, 10.0)),
    ):
        e = np.sort(np.array([getattr(r, key) for r in records], float))
        e = e[np.isfinite(e)]
        if len(e):
            ax.step(np.maximum(e, 1e-4), np.arange(1, len(e) + 1) / n, where="post")
            ax.set_xscale("log")
        for m in marks:
            ax.axvline(m, color="grey", lw=0.6, ls="--")
        ax.set_xlabel(f"{key.split('_')[0]} error ({unit})")
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("fraction of queries")
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def evaluate_localization(run: QueryRun, *, progress: bool = True) -> dict[str, Any]:
    """Metrics dict (module docstring) of one configuration on a build's query run."""
    records = query_records(run, progress=progress)
    return {**localization_metrics(records), "records": [asdict(r) for r in records]}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_scene_arguments(parser, queries=50)
    add_pipeline_arguments(parser)


def run(args: argparse.Namespace) -> int:
    query_run = QueryRun.from_args(args)
    metrics = evaluate_localization(query_run)
    records = [FrameRecord(**r) for r in metrics["records"]]
    settings = {"scene": args.scene, **query_run.settings()}
    lost = {}
    for r in records:
        if r.status == "lost":
            lost[r.reason] = lost.get(r.reason, 0) + 1
    sections = [
        "## Settings\n\n" + markdown_table(["setting", "value"], list(settings.items())),
        "## Lost queries by reason\n\n" + markdown_table(["reason", "count"], sorted(lost.items()))
        if lost
        else "No query was lost.",
        "Medians are over localized queries; recalls count lost queries as failures. "
        "Paper (7-Scenes, VGGT backbone): 0.03 m / 0.86 deg median.",
    ]
    fig = error_cdf_figure(records, f"{args.scene}: {args.backbone}, {args.retrieval} / {args.averaging}")
    write_report(args.out, "Localization", {**metrics, "settings": settings}, sections, {"errors.png": fig})
    return 0
