"""Localization protocol: pose error, recall and gross errors of VGP-Nav on scenes' query runs.

``vgpnav eval localization SCENE [SCENE ...] --backbone B [--queries N] [--retrieval geometry|topk]
[--averaging weighted|single] [--k 10] [--perception-mode paper|temporal] --out DIR [--size WxH]
[--seed S] [--build DIR]``

Per scene, ``report.json`` holds :func:`~vgpnav_env.eval.perception_runs.localization_metrics`
(``recall_5cm_5deg``, ``recall_25cm_2deg``, ``recall_50cm_5deg``, ``n_gross``, ``gross_rate``,
``lost_rate``, ``lost_by_reason``, ``retrieval_recall``, median and mean errors), the CPU seconds
per frame, the settings and one record per query; ``report.md`` adds the per-frame table, the
error CDF (``errors.png``) and the worst frames (``worst.png``). Several scenes: one report per
scene plus a table across them (:mod:`vgpnav_env.eval.query_reports`).

``--perception-mode temporal`` perceives the frames in order with the state estimate (tracking,
the EKF on simulated wheel odometry; :func:`~vgpnav_env.eval.perception_runs.perceive_queries`):
the metrics are the temporal run's, plus its estimate's (:func:`~vgpnav_env.eval.perception_runs.
temporal_metrics`), and ``modes`` puts them beside the same frames in paper mode (run as well).
"""

from __future__ import annotations

import argparse
from dataclasses import asdict, replace
from typing import Any

from matplotlib.figure import Figure

from vgpnav_env.eval.perception_runs import (
    QueryRun,
    add_perception_mode_argument,
    add_pipeline_arguments,
    add_scene_arguments,
    query_records,
    temporal_metrics,
)
from vgpnav_env.eval.query_reports import localization_summary, run_scenes
from vgpnav_env.eval.report import markdown_table
from vgpnav_env.eval.workers import Workers, add_worker_arguments

#: The table across scenes.
COLUMNS = (
    "n_queries",
    "recall_5cm_5deg",
    "recall_25cm_2deg",
    "recall_50cm_5deg",
    "n_gross",
    "gross_rate",
    "lost_rate",
    "lost_by_reason",
    "retrieval_recall",
    "confidence_auc",
    "median_translation_m",
    "mean_translation_m",
    "median_rotation_deg",
    "mean_rotation_deg",
    "cpu_s_per_frame",
)
#: The columns of the modes table (temporal mode).
MODE_COLUMNS = (
    "lost_rate",
    "n_gross",
    "recall_5cm_5deg",
    "median_translation_m",
    "cpu_s_per_frame",
    "tracked_rate",
    "no_estimate_rate",
    "estimate_mean_m",
    "estimate_p95_m",
    "estimate_gross_rate",
)


def evaluate_localization(
    run: QueryRun, *, workers: Workers | None = None, progress: bool = True
) -> dict[str, Any]:
    """Metrics dict (module docstring) of one configuration on a build's query run; ``workers``
    (default: this process) perceive the frames. Temporal mode adds the estimate's metrics and
    ``modes``: the table's columns (:data:`MODE_COLUMNS`) for each mode, the same frames run in
    paper mode too."""
    records = query_records(run, workers=workers, progress=progress)
    metrics = {**localization_summary(records), **temporal_metrics(records)}
    if run.mode == "temporal":
        paper_records = query_records(replace(run, mode="paper"), workers=workers, progress=progress)
        paper = localization_summary(paper_records)
        metrics["modes"] = {
            mode: {k: m.get(k, float("nan")) for k in MODE_COLUMNS}
            for mode, m in (("paper", paper), ("temporal", metrics))
        }
    return {**metrics, "records": [asdict(r) for r in records]}


def _evaluate(run: QueryRun, workers: Workers) -> tuple[dict[str, Any], dict[str, Figure]]:
    return evaluate_localization(run, workers=workers), {}


def headline(scene: str, m: dict[str, Any]) -> str:
    return (
        f"localization {scene}: {m['n_queries']} queries, lost {m['lost_rate']:.0%}, gross "
        f"{m['n_gross']}, recall 5 cm / 5 deg {m['recall_5cm_5deg']:.2f}, median "
        f"{m['median_translation_m']:.3f} m / {m['median_rotation_deg']:.2f} deg"
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_scene_arguments(parser, queries=50, several=True)
    add_pipeline_arguments(parser)
    add_perception_mode_argument(parser, default="paper")
    add_worker_arguments(parser)


def paper_note(metrics: dict[str, Any]) -> list[str]:
    sections = ["Paper (7-Scenes, VGGT backbone): 0.03 m / 0.86 deg median."]
    if "modes" in metrics:
        rows = [(mode, *m.values()) for mode, m in metrics["modes"].items()]
        sections.append(
            "## Perception modes\n\nThe same frames per frame (paper) and in order with the state "
            "estimate (temporal: tracking, EKF on simulated wheel odometry). `estimate_*`: the EKF's "
            "horizontal error over the frames with an estimate; `no_estimate_rate`: frames before "
            "its first (confirmed) estimate.\n\n" + markdown_table(["mode", *MODE_COLUMNS], rows)
        )
    return sections


def run(args: argparse.Namespace) -> int:
    return run_scenes(args, "Localization", _evaluate, COLUMNS, headline, paper_note)
