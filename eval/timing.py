"""Timing protocol: seconds per frame of every VGP-Nav module (paper Table VI) and of its steps.

``vgpnav eval timing SCENE --backbone B [--queries N] [--k 10] [--perception-mode M] --out DIR``

Runs the pipeline in this one process (parallel workers would time their sharing of the cores) over
``N`` evenly spaced query frames (the first frame warms up caches and is not timed) and reports,
over the frames that localized (all frames if none did; a lost frame skips the later stages), per
stage (retrieval, backbone, motion_averaging, scale_recovery, verification, occupancy, total) the
median wall seconds (``seconds_per_frame``, with the 90th percentile) and the median CPU seconds of
the process over all its threads (``cpu_seconds_per_module``; the whole call:
``cpu_seconds_per_frame``) beside the paper's figures (VGGT on an RTX 5090), and the steps inside
the stages (``steps``: mean wall and CPU seconds per frame over the same frames, summed over a
frame's rounds), e.g. the classical backbone's ``features``, ``matching``, ``two_view``,
``scale_linking``, ``plane_sweep`` and ``completion`` and the occupancy's ``posed_depth``,
``completion`` and ``fusion``. ``threads`` records the thread pools the process used
(:func:`~vgpnav_env.perception.backbones.threads.thread_report`). Wall time is what a robot waits;
it drops below the CPU time when the backbone's threads run on several free cores and rises above
it when other processes share the cores (the report records the CPU count and the load average).
CPU seconds are less sensitive to that load.
"""

from __future__ import annotations

import argparse
import os
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from vgpnav_env.eval.perception_runs import (
    QueryRun,
    add_perception_mode_argument,
    add_pipeline_arguments,
    add_scene_arguments,
    query_records,
)
from vgpnav_env.eval.report import RunClock, markdown_table, print_headline, run_settings, write_report
from vgpnav_env.perception.backbones.threads import thread_report
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
    steps = sorted({k for r in used for k in r.timings if "." in k and not k.endswith("_cpu")})
    return {
        "seconds_per_frame": {k: float(np.nanmedian(v)) for k, v in wall.items()},
        "seconds_p90": {k: float(np.nanpercentile(v, 90)) for k, v in wall.items()},
        "cpu_seconds_per_module": {k: median(cpu_keys[k]) for k in TIMING_KEYS},
        "cpu_seconds_per_frame": median("cpu"),
        "steps": {
            k: {
                "wall": float(np.mean([r.timings.get(k, 0.0) for r in used])),
                "cpu": float(np.mean([r.timings.get(f"{k}_cpu", 0.0) for r in used])),
            }
            for k in steps
        },
        "cpu_mean_per_frame": float(np.mean([r.timings.get("cpu", np.nan) for r in used])),
        "threads": thread_report(),
        "total_all_frames": median("total", timed),
        "cpu_all_frames": median("cpu", timed),
        "paper_seconds_per_frame": PAPER_SECONDS,
        "n_frames": len(used),
        "n_lost": sum(r.status == "lost" for r in timed),
        "cpu_count": os.cpu_count(),
        "load_average": list(os.getloadavg()),
    }


def _plain(value: Any) -> str:
    """A thread report's value as one table cell."""
    if isinstance(value, dict):
        return ", ".join(f"{k} {v}" for k, v in value.items())
    return str(value)


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
    add_perception_mode_argument(parser, default="paper")


def run(args: argparse.Namespace) -> int:
    clock = RunClock()
    query_run = QueryRun.from_args(args)
    metrics = evaluate_timing(query_run)
    settings = {"scene": args.scene, **query_run.settings(), **run_settings(clock)}
    wall, p90, cpu = metrics["seconds_per_frame"], metrics["seconds_p90"], metrics["cpu_seconds_per_module"]
    rows = [(k, wall[k], p90[k], cpu[k], PAPER_SECONDS[k]) for k in TIMING_KEYS]
    steps, threads = metrics["steps"], metrics["threads"]
    sections = [
        f"Backbone `{args.backbone}`, k = {args.k}, retrieval {args.retrieval}, averaging {args.averaging}, "
        f"perception mode {args.perception_mode}; "
        f"{metrics['n_frames']} timed frames ({metrics['n_lost']} lost) on {metrics['cpu_count']} CPUs "
        f"(load average {metrics['load_average'][0]:.1f}). Medians over the localized frames; over all "
        f"frames, lost ones included: {metrics['total_all_frames']:.3f} s wall, "
        f"{metrics['cpu_all_frames']:.3f} CPU s. CPU seconds count every thread of the process: wall < CPU "
        "when the backbone's threads run on free cores, wall > CPU when other processes share them.",
        "## Seconds per frame\n\n"
        + markdown_table(
            ["module", "wall (median)", "wall (p90)", "CPU s (median)", "paper (RTX 5090, VGGT)"], rows
        ),
        "## Steps inside the modules (mean s per frame, all rounds of a frame)\n\n"
        + markdown_table(["step", "wall", "CPU s"], [(k, v["wall"], v["cpu"]) for k, v in steps.items()])
        + f"\n\nMean CPU s per frame: {metrics['cpu_mean_per_frame']:.3f}.",
        "## Threads\n\n" + markdown_table(["pool", "threads"], [(k, _plain(v)) for k, v in threads.items()]),
    ]
    figures = {"timing.png": timing_figure(metrics)}
    write_report(args.out, "Per-module timing", metrics, sections, figures, settings=settings)
    print_headline(
        f"perception per frame: {wall['total']:.3f} s wall, {metrics['cpu_seconds_per_frame']:.3f} CPU s "
        f"(paper: {PAPER_SECONDS['total']:.3f} s on an RTX 5090)",
        args.out,
    )
    return 0
