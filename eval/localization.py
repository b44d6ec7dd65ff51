"""Localization protocol: pose error, recall and gross errors of VGP-Nav on scenes' query runs.

``vgpnav eval localization SCENE [SCENE ...] --backbone B [--queries N] [--retrieval geometry|topk]
[--averaging weighted|single] [--k 10] --out DIR [--size WxH] [--seed S] [--build DIR]``

Per scene, ``report.json`` holds :func:`~vgpnav_env.eval.perception_runs.localization_metrics`
(``recall_5cm_5deg``, ``recall_25cm_2deg``, ``recall_50cm_5deg``, ``n_gross``, ``gross_rate``,
``lost_rate``, ``lost_by_reason``, ``retrieval_recall``, median and mean errors), the CPU seconds
per frame, the settings and one record per query; ``report.md`` adds the per-frame table, the
error CDF (``errors.png``) and the worst frames (``worst.png``). Several scenes: one report per
scene plus a table across them (:mod:`vgpnav_env.eval.query_reports`).
"""

from __future__ import annotations

import argparse
from dataclasses import asdict
from typing import Any

from matplotlib.figure import Figure

from vgpnav_env.eval.perception_runs import (
    QueryRun,
    add_pipeline_arguments,
    add_scene_arguments,
    query_records,
)
from vgpnav_env.eval.query_reports import localization_summary, run_scenes
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


def evaluate_localization(
    run: QueryRun, *, workers: Workers | None = None, progress: bool = True
) -> dict[str, Any]:
    """Metrics dict (module docstring) of one configuration on a build's query run; ``workers``
    (default: this process) perceive the frames."""
    records = query_records(run, workers=workers, progress=progress)
    return {**localization_summary(records), "records": [asdict(r) for r in records]}


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
    add_worker_arguments(parser)


def paper_note(metrics: dict[str, Any]) -> list[str]:
    return ["Paper (7-Scenes, VGGT backbone): 0.03 m / 0.86 deg median."]


def run(args: argparse.Namespace) -> int:
    return run_scenes(args, "Localization", _evaluate, COLUMNS, headline, paper_note)
