"""Timing protocol: seconds per frame of every VGP-Nav module (paper Table VI).

``vgpnav eval timing SCENE --backbone B [--queries N] [--k 10] --out DIR [--build DIR]``

Runs the pipeline over ``N`` evenly spaced query frames (the first frame warms up caches and
is not timed) and reports, over the frames that localized (all frames if none did; a lost frame
skips the later stages), the median seconds per stage in ``seconds_per_frame`` (retrieval,
backbone, motion_averaging, scale_recovery, occupancy, total) beside the paper's figures
(VGGT on an RTX 5090), plus the backbone's own breakdown when it reports one. Wall timings
depend on the machine's load: the report records the CPU count and load average, and the median
CPU seconds per frame (``cpu_seconds_per_frame``, the process's CPU time over all its threads),
which other processes sharing the cores inflate far less.
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
from vgpnav_env.eval.report import markdown_table, write_report
from vgpnav_env.perception.pipeline import TIMING_KEYS

#: Paper Table VI, seconds per frame (VGGT backbone, RTX 5090); occupancy is not listed there.
PAPER_SECONDS = {
    "retrieval": 0.027,
    "backbone": 0.420,
    "motion_averaging": 0.005,
    "scale_recovery": 0.040,
    "occupancy": None,
    "total": 0.492,
}


def evaluate_timing(run: QueryRun, *, progress: bool = True) -> dict[str, Any]:
    """``seconds_per_frame`` medians per stage (and per backbone sub-stage), with percentiles."""
    records = query_records(run, progress=progress)
    timed = records[1:] or records
    used = [r for r in timed if r.status == "localized"] or timed
    table = {k: np.array([r.timings.get(k, np.nan) for r in used], float) for k in TIMING_KEYS}
    sub = sorted({k for r in used for k in r.timings} - set(TIMING_KEYS) - {"cpu"})
    return {
        "seconds_per_frame": {k: float(np.nanmedian(v)) for k, v in table.items()},
        "cpu_seconds_per_frame": float(np.nanmedian([r.timings.get("cpu", np.nan) for r in used])),
        "seconds_p90": {k: float(np.nanpercentile(v, 90)) for k, v in table.items()},
        "backbone_seconds": {k: float(np.nanmedian([r.timings.get(k, np.nan) for r in used])) for k in sub},
        "total_all_frames": float(np.median([r.timings.get("total", np.nan) for r in timed])),
        "paper_seconds_per_frame": PAPER_SECONDS,
        "n_frames": len(used),
        "n_lost": sum(r.status == "lost" for r in timed),
        "cpu_count": os.cpu_count(),
        "load_average": list(os.getloadavg()),
    }


def timing_figure(metrics: dict[str, Any]) -> Figure:
    fig = Figure(figsize=(7, 3.2))
    ax = fig.subplots()
    keys = [k for k in TIMING_KEYS if k != "total"]
    x = np.arange(len(keys))
    ours = [metrics["seconds_per_frame"][k] for k in keys]
    paper = [PAPER_SECONDS[k] or 0.0 for k in keys]
    ax.bar(x - 0.2, ours, 0.4, label="ours (median, CPU)")
    ax.bar(x + 0.2, paper, 0.4, label="paper (RTX 5090)")
    ax.set_xticks(x, [k.replace("_", "\n") for k in keys])
    ax.set_ylabel("seconds per frame")
    ax.legend()
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    return fig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_scene_arguments(parser, queries=20)
    add_pipeline_arguments(parser)


def run(args: argparse.Namespace) -> int:
    metrics = evaluate_timing(QueryRun.from_args(args))
    rows = [
        (k, metrics["seconds_per_frame"][k], metrics["seconds_p90"][k], PAPER_SECONDS[k]) for k in TIMING_KEYS
    ]
    sections = [
        f"Backbone `{args.backbone}`, k = {args.k}, retrieval {args.retrieval}, averaging {args.averaging}; "
        f"{metrics['n_frames']} timed frames on {metrics['cpu_count']} CPUs "
        f"(load average {metrics['load_average'][0]:.1f}); median total over all frames, lost ones "
        f"included: {metrics['total_all_frames']:.3f} s; median CPU time per frame (all threads): "
        f"{metrics['cpu_seconds_per_frame']:.3f} s.",
        "## Seconds per frame\n\n"
        + markdown_table(["module", "ours (median)", "ours (p90)", "paper (RTX 5090, VGGT)"], rows),
        "## Backbone breakdown (median s)\n\n"
        + markdown_table(["step", "seconds"], list(metrics["backbone_seconds"].items())),
    ]
    write_report(args.out, "Per-module timing", metrics, sections, {"timing.png": timing_figure(metrics)})
    return 0
