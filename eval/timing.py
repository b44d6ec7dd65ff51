"""Timing protocol: seconds per frame of every VGP-Nav module (paper Table VI).

``vgpnav eval timing SCENE --backbone B [--queries N] [--k 10] --out DIR [--build DIR]``

Runs the pipeline in this one process (parallel workers would time their sharing of the cores) over
``N`` evenly spaced query frames (the first frame warms up caches and is not timed) and reports,
over the frames that localized (all frames if none did; a lost frame skips the later stages), per
stage (retrieval, backbone, motion_averaging, scale_recovery, occupancy, total) the median wall
seconds (``seconds_per_frame``, with the 90th percentile) and the median CPU seconds of the process
over all its threads (``cpu_seconds_per_module``; the whole call: ``cpu_seconds_per_frame``) beside
the paper's figures (VGGT on an RTX 5090), plus the backbone's own breakdown when it reports one
(``backbone_seconds``, wall and ``*_cpu``). Wall time is what a robot waits; it drops below the CPU
time when the backbone's threads run on several free cores and rises above it when other processes
share the cores (the report records the CPU count and the load average). CPU seconds are less
sensitive to that load.
"""

from __future__ import annotations

import argparse
import os
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from vgpnav_env.eval.perception_runs import (
    QueryRun,
    add_pipeline_arguments,
    add_scene_arguments,
    query_records,
)
from vgpnav_env.eval.report import RunClock, markdown_table, print_headline, run_settings, write_report
from vgpnav_env.perception.pipeline import TIMING_KEYS

#: Paper Table VI, seconds per frame (VGGT backbone, RTX 5090); verification and occupancy are not
#: listed there.
PAPER_SECONDS = {
    "retrieval": 0.027,
    "backbone": 0.420,
    "motion_averaging": 0.005,
    "scale_recovery": 0.040,
    "verification": None,
    "occupancy": None,
    "total": 0.492,
}


def evaluate_timing(run: QueryRun, *, progress: bool = True) -> dict[str, Any]:
    """Median wall and CPU seconds per stage (and per backbone sub-stage), with wall percentiles."""
    records = query_records(run, progress=progress)
    timed = records[1:] or records
    used = [r for r in timed if r.status == "localized"] or timed

    def median(key: str, rows: list = used) -> float:
        values = np.array([r.timings.get(key, np.nan) for r in rows], float)
        return float(np.nanmedian(values)) if np.isfinite(values).any() else float("nan")

    wall = {k: np.array([r.timings.get(k, np.nan) for r in used], float) for k in TIMING_KEYS}
    cpu_keys = {k: "cpu" if k == "total" else f"{k}_cpu" for k in TIMING_KEYS}
    sub = sorted({k for r in used for k in r.timings if k.startswith("backbone.")})
    return {
        "seconds_per_frame": {k: float(np.nanmedian(v)) for k, v in wall.items()},
        "seconds_p90": {k: float(np.nanpercentile(v, 90)) for k, v in wall.items()},
        "cpu_seconds_per_module": {k: median(cpu_keys[k]) for k in TIMING_KEYS},
        "cpu_seconds_per_frame": median("cpu"),
        "backbone_seconds": {k.removeprefix("backbone."): median(k) for k in sub},
        "total_all_frames": median("total", timed),
        "cpu_all_frames": median("cpu", timed),
        "paper_seconds_per_frame": PAPER_SECONDS,
        "n_frames": len(used),
        "n_lost": sum(r.status == "lost" for r in timed),
        "cpu_count": os.cpu_count(),
        "load_average": list(os.getloadavg()),
    }


def timing_figure(metrics: dict[str, Any]) -> Figure:
    fig = Figure(figsize=(7.5, 3.4))
    ax = fig.subplots()
    keys = [k for k in TIMING_KEYS if k != "total"]
    x = np.arange(len(keys))
    wall = [metrics["seconds_per_frame"][k] for k in keys]
    cpu = [metrics["cpu_seconds_per_module"][k] for k in keys]
    paper = [PAPER_SECONDS[k] or 0.0 for k in keys]
    ax.bar(x - 0.27, wall, 0.27, label="ours, wall (median)")
    ax.bar(x, cpu, 0.27, label="ours, CPU s (median)")
    ax.bar(x + 0.27, paper, 0.27, label="paper (RTX 5090)")
    ax.set_xticks(x, [k.replace("_", "\n") for k in keys])
    ax.set_ylabel("seconds per frame")
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    return fig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_scene_arguments(parser, queries=20)
    add_pipeline_arguments(parser)


def run(args: argparse.Namespace) -> int:
    clock = RunClock()
    query_run = QueryRun.from_args(args)
    metrics = evaluate_timing(query_run)
    settings = {"scene": args.scene, **query_run.settings(), **run_settings(clock)}
    wall, p90, cpu = metrics["seconds_per_frame"], metrics["seconds_p90"], metrics["cpu_seconds_per_module"]
    rows = [(k, wall[k], p90[k], cpu[k], PAPER_SECONDS[k]) for k in TIMING_KEYS]
    breakdown = metrics["backbone_seconds"]
    steps = [k for k in breakdown if not k.endswith("_cpu")]
    sections = [
        f"Backbone `{args.backbone}`, k = {args.k}, retrieval {args.retrieval}, averaging {args.averaging}; "
        f"{metrics['n_frames']} timed frames ({metrics['n_lost']} lost) on {metrics['cpu_count']} CPUs "
        f"(load average {metrics['load_average'][0]:.1f}). Medians over the localized frames; over all "
        f"frames, lost ones included: {metrics['total_all_frames']:.3f} s wall, "
        f"{metrics['cpu_all_frames']:.3f} CPU s. CPU seconds count every thread of the process: wall < CPU "
        "when the backbone's threads run on free cores, wall > CPU when other processes share them.",
        "## Seconds per frame\n\n"
        + markdown_table(
            ["module", "wall (median)", "wall (p90)", "CPU s (median)", "paper (RTX 5090, VGGT)"], rows
        ),
        "## Backbone breakdown (median s)\n\n"
        + markdown_table(
            ["step", "wall", "CPU s"],
            [(k, breakdown[k], breakdown.get(f"{k}_cpu", float("nan"))) for k in steps],
        ),
    ]
    figures = {"timing.png": timing_figure(metrics)}
    write_report(args.out, "Per-module timing", metrics, sections, figures, settings=settings)
    print_headline(
        f"perception per frame: {wall['total']:.3f} s wall, {metrics['cpu_seconds_per_frame']:.3f} CPU s "
        f"(paper: {PAPER_SECONDS['total']:.3f} s on an RTX 5090)",
        args.out,
    )
    return 0
