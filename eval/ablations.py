"""Ablation protocol: paper Tables IV (localization) and V (metric perception) on our scenes.

``vgpnav eval ablations SCENE [--backbone B] [--queries N] [--k 10] [--perception-mode paper|temporal]
--out DIR [--build DIR]``

Table IV switches the geometry-aware retrieval (else top-k) and the weighted motion averaging
(else the single best reference, placed with the ground-anchored scale); Table V adds and removes
the ground-anchored scale recovery (off = the backbone's unknown scale). The six distinct
configurations run once each over the same query frames, in ``--perception-mode`` (default
paper: every frame on its own, as published); the full pipeline also runs in the other mode, and
``modes`` holds both (``report.md``'s "Perception modes" table). ``report.json`` holds
``table_iv`` and ``table_v`` (our numbers beside the paper's) and every configuration's metrics.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from vgpnav_env.arguments import positive_int_arg
from vgpnav_env.eval.perception_runs import (
    QueryRun,
    add_backbone_arguments,
    add_perception_mode_argument,
    add_scene_arguments,
    backbone_options,
    localization_metrics,
    perception_metrics,
    query_records,
    resolve_build,
    temporal_metrics,
)
from vgpnav_env.eval.query_reports import time_metrics
from vgpnav_env.eval.report import RunClock, markdown_table, print_headline, run_settings, write_report
from vgpnav_env.eval.workers import Workers, add_worker_arguments, workers_from_args
from vgpnav_env.perception.pipeline import PerceptionConfig

#: name -> (retrieval, averaging, scale recovery).
CONFIGS: dict[str, tuple[str, str, bool]] = {
    "topk-single-scale": ("topk", "single", True),
    "geometry-single-scale": ("geometry", "single", True),
    "topk-weighted-scale": ("topk", "weighted", True),
    "geometry-weighted-scale": ("geometry", "weighted", True),
    "topk-single-noscale": ("topk", "single", False),
    "topk-weighted-noscale": ("topk", "weighted", False),
}
#: The "Perception modes" table: the full pipeline per frame (paper) and in order (temporal).
MODE_COLUMNS = (
    "lost_rate",
    "n_gross",
    "recall_5cm_5deg",
    "median_translation_m",
    "acc_m",
    "comp_m",
    "cpu_s_per_frame",
    "tracked_rate",
    "estimate_mean_m",
    "estimate_p95_m",
    "estimate_gross_rate",
)
#: Paper Table IV (7-Scenes): (geometry retrieval, weighted averaging, config, cm, deg).
TABLE_IV = [
    (False, False, "topk-single-scale", 11.3, 0.90),
    (True, False, "geometry-single-scale", 10.8, 0.87),
    (False, True, "topk-weighted-scale", 3.4, 0.89),
    (True, True, "geometry-weighted-scale", 3.0, 0.86),
]
#: Paper Table V (Home): (weighted averaging, scale recovery, geometry retrieval, config, Acc, Comp).
TABLE_V = [
    (False, False, False, "topk-single-noscale", 1.74, 2.68),
    (True, False, False, "topk-weighted-noscale", 0.61, 1.12),
    (True, True, False, "topk-weighted-scale", 0.09, 0.05),
    (True, True, True, "geometry-weighted-scale", 0.08, 0.03),
]


def evaluate_ablations(
    run: QueryRun, *, workers: Workers | None = None, progress: bool = True
) -> dict[str, Any]:
    """Metrics of every configuration (``run`` with its config's switches set, in ``run.mode``), the
    two tables and ``modes``: the full pipeline in both perception modes (:data:`MODE_COLUMNS`);
    ``workers`` (default: this process) perceive the frames, keeping the database and the backbone
    between configurations."""
    k, n_queries = run.config.retrieval.k, run.n_queries
    own = workers is None
    workers = workers or Workers(1, progress=progress)
    results: dict[str, dict[str, Any]] = {}
    try:
        for name, (retrieval, averaging, scale) in CONFIGS.items():
            config = PerceptionConfig.ablation(retrieval=retrieval, averaging=averaging, scale=scale, k=k)
            records = query_records(replace(run, config=config), workers=workers)
            results[name] = _config_metrics(records)
        full = replace(run, config=PerceptionConfig.ablation(k=k))
        other = "temporal" if run.mode == "paper" else "paper"
        modes = {
            run.mode: results["geometry-weighted-scale"],
            other: _config_metrics(query_records(replace(full, mode=other), workers=workers)),
        }
    finally:
        if own:
            workers.close()
    table_iv = [
        {
            "geometry_retrieval": geo,
            "weighted_averaging": wma,
            "config": name,
            "paper_translation_cm": cm,
            "paper_rotation_deg": deg,
            "translation_cm": 100.0 * results[name]["localization"]["median_translation_m"],
            "rotation_deg": results[name]["localization"]["median_rotation_deg"],
            "recall_5cm_5deg": results[name]["localization"]["recall_5cm_5deg"],
            "n_lost": results[name]["localization"]["n_lost"],
        }
        for geo, wma, name, cm, deg in TABLE_IV
    ]
    table_v = [
        {
            "weighted_averaging": wma,
            "scale_recovery": scale,
            "geometry_retrieval": geo,
            "config": name,
            "paper_acc_m": acc,
            "paper_comp_m": comp,
            "acc_m": results[name]["perception"]["acc_m"],
            "comp_m": results[name]["perception"]["comp_m"],
            "n_frames": results[name]["perception"]["n_frames"],
        }
        for wma, scale, geo, name, acc, comp in TABLE_V
    ]
    modes_table = {
        mode: {k: {**m["localization"], **m["perception"], **m["temporal"]}.get(k, float("nan"))
               for k in MODE_COLUMNS}
        for mode, m in sorted(modes.items(), key=lambda kv: kv[0] != "paper")
    }  # fmt: skip
    return {
        "table_iv": table_iv,
        "table_v": table_v,
        "configs": results,
        "modes": modes_table,
        "n_queries": n_queries,
        "k": k,
        "mode": run.mode,
    }


def _config_metrics(records: list) -> dict[str, Any]:
    """One configuration's localization, perception and (temporal mode) state-estimate metrics."""
    return {
        "localization": {**localization_metrics(records), **time_metrics(records)},
        "perception": perception_metrics(records),
        "temporal": temporal_metrics(records),
    }


def retrieval_comparison(configs: dict[str, dict[str, Any]]) -> str:
    """One paragraph: does Alg. 1 help here (weighted averaging, scale recovery on), with numbers."""
    geo = configs["geometry-weighted-scale"]["localization"]
    top = configs["topk-weighted-scale"]["localization"]
    helps = (geo["n_lost"], -geo["recall_5cm_5deg"]) <= (top["n_lost"], -top["recall_5cm_5deg"])
    numbers = (
        f"geometry-aware (Alg. 1) vs top-k: lost {geo['n_lost']} vs {top['n_lost']}, recall 5cm/5deg "
        f"{geo['recall_5cm_5deg']:.2f} vs {top['recall_5cm_5deg']:.2f}, median "
        f"{100 * geo['median_translation_m']:.2f} vs {100 * top['median_translation_m']:.2f} cm."
    )
    if helps:
        return f"Alg. 1 helps or ties here, as in the paper's Table IV: {numbers}"
    return (
        f"Alg. 1 does NOT help here: {numbers} In a database covering a whole home, the top-4k pool "
        "spans several rooms and the diversity term favours references looking elsewhere (no "
        "overlap with the query), while the paper's 7-Scenes pools view one small scene; the "
        "pipeline's second round (pose-guided references around the first verified pairs) narrows "
        "but does not close the gap."
    )


def ablation_figure(metrics: dict[str, Any]) -> Figure:
    """Ours beside the paper: Table IV median translation error and Table V Acc / Comp per
    configuration (log scale: the configurations span two orders of magnitude; values below 0.01 cm
    and 1 mm are drawn at that floor)."""
    fig = Figure(figsize=(11, 3.8))
    left, right = fig.subplots(1, 2)
    iv, v = metrics["table_iv"], metrics["table_v"]
    x = np.arange(len(iv))
    for offset, key, label in ((-0.2, "translation_cm", "ours"), (0.2, "paper_translation_cm", "paper")):
        left.bar(x + offset, np.maximum([r[key] for r in iv], 0.01), 0.4, label=label)
    left.set_xticks(x, [r["config"].replace("-", "\n", 1) for r in iv], fontsize=7)
    left.set_ylabel("translation error (cm)")
    left.set_title("Table IV: localization", fontsize=9)
    x = np.arange(len(v))
    bars = {"acc_m": "ours Acc", "comp_m": "ours Comp"}
    bars |= {"paper_acc_m": "paper Acc", "paper_comp_m": "paper Comp"}
    for offset, (key, label) in zip((-0.3, -0.1, 0.1, 0.3), bars.items(), strict=True):
        right.bar(x + offset, np.maximum([r[key] for r in v], 1e-3), 0.2, label=label)
    right.set_xticks(x, [r["config"].replace("-", "\n", 1) for r in v], fontsize=7)
    right.set_ylabel("metres")
    right.set_title("Table V: metric perception", fontsize=9)
    for ax in (left, right):
        ax.set_yscale("log")
        ax.grid(axis="y", alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def _mark(flag: bool) -> str:
    return "yes" if flag else "no"


#: The columns of the report's Table IV and Table V, as (header, record key); the switches (the
#: first keys, booleans) show as yes / no.
TABLE_IV_COLUMNS = (
    ("geometry retrieval", "geometry_retrieval"),
    ("weighted MA", "weighted_averaging"),
    ("paper cm", "paper_translation_cm"),
    ("paper deg", "paper_rotation_deg"),
    ("ours cm", "translation_cm"),
    ("ours deg", "rotation_deg"),
    ("recall 5cm/5deg", "recall_5cm_5deg"),
    ("lost", "n_lost"),
)
TABLE_V_COLUMNS = (
    ("weighted MA", "weighted_averaging"),
    ("scale recovery", "scale_recovery"),
    ("geometry retrieval", "geometry_retrieval"),
    ("paper Acc", "paper_acc_m"),
    ("paper Comp", "paper_comp_m"),
    ("ours Acc", "acc_m"),
    ("ours Comp", "comp_m"),
    ("frames", "n_frames"),
)
_SWITCHES = ("geometry_retrieval", "weighted_averaging", "scale_recovery")


def _table(columns: tuple[tuple[str, str], ...], records: list[dict[str, Any]], fmt: str) -> str:
    """A Markdown table of ``records`` with the ``columns`` (header, key), numbers as ``fmt``."""
    rows = [tuple(_mark(r[k]) if k in _SWITCHES else r[k] for _, k in columns) for r in records]
    return markdown_table([header for header, _ in columns], rows, fmt)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_scene_arguments(parser, queries=20)
    add_backbone_arguments(parser)
    parser.add_argument("--k", type=positive_int_arg, default=10, help="number of references (default 10)")
    add_perception_mode_argument(parser, default="paper")
    add_worker_arguments(parser)


def run(args: argparse.Namespace) -> int:
    clock = RunClock()
    options = backbone_options(args)
    build = resolve_build(args)
    config = PerceptionConfig.ablation(k=args.k)
    query_run = QueryRun(build, args.backbone, options, config, args.queries, args.seed, args.perception_mode)
    with workers_from_args(args) as workers:
        metrics = evaluate_ablations(query_run, workers=workers)
    settings = {"scene": args.scene, **query_run.settings()}
    for switch in ("retrieval", "averaging", "scale_recovery"):
        settings[switch] = "per configuration"
    settings |= run_settings(clock, workers.where, workers.cpu_seconds)
    sections = [
        "Paper Table IV is on 7-Scenes (VGGT backbone), Table V on its Home scene.",
        retrieval_comparison(metrics["configs"]),
        "## Table IV: localization (median over localized queries)\n\n"
        + _table(TABLE_IV_COLUMNS, metrics["table_iv"], ".2f"),
        "## Table V: metric perception (m)\n\n" + _table(TABLE_V_COLUMNS, metrics["table_v"], ".3f"),
    ]
    modes = [(mode, *m.values()) for mode, m in metrics["modes"].items()]
    sections.append(
        "## Perception modes (full pipeline)\n\nThe same frames per frame (paper) and in order with "
        "the state estimate (temporal: tracking, EKF on simulated wheel odometry; `estimate_*` is "
        "the EKF's horizontal error over the frames with an estimate). The tables above are in "
        f"{metrics['mode']} mode.\n\n" + markdown_table(["mode", *MODE_COLUMNS], modes)
    )
    figures = {"ablations.png": ablation_figure(metrics)}
    write_report(args.out, "Ablations (paper Tables IV and V)", metrics, sections, figures, settings=settings)
    full, none = metrics["configs"]["geometry-weighted-scale"], metrics["configs"]["topk-single-noscale"]
    print_headline(
        f"ablations {args.scene} ({args.backbone}): full pipeline median "
        f"{100 * full['localization']['median_translation_m']:.1f} cm, "
        f"Acc {full['perception']['acc_m']:.3f} m; "
        f"without WMA and scale {100 * none['localization']['median_translation_m']:.1f} cm, "
        f"Acc {none['perception']['acc_m']:.3f} m",
        args.out,
    )
    return 0
