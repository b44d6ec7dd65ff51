"""Reports of the query-frame protocols (localization, perception), for one scene or several.

``vgpnav eval localization|perception SCENE [SCENE ...]`` runs each scene's query run (one
:class:`~vgpnav_env.eval.perception_runs.QueryRun` per scene, same settings) and writes

- one scene: ``OUT/report.json`` + ``OUT/report.md``;
- several: one report per scene in ``OUT/<scene>/`` (``home:1`` -> ``home-1``) and
  ``OUT/report.json`` + ``report.md`` with one table across the scenes (:func:`run_scenes`).

Every scene report holds the honest metrics (DESIGN.md "Metrics"): recalls, ``n_gross`` /
``gross_rate``, lost frames by reason, retrieval recall, median and mean errors, CPU seconds per
frame, a per-frame table, the error CDF (``errors.png``) and the worst frames, each query beside
the references its pose came from (``worst.png``).
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from vgpnav_env.eval.perception_runs import (
    CANDIDATE_CLASSES,
    GROSS_ERROR,
    RECALL_THRESHOLDS,
    FrameRecord,
    QueryRun,
    confidence_roc,
    is_gross,
    localization_metrics,
    pose_errors,
)
from vgpnav_env.eval.report import (
    RunClock,
    markdown_table,
    plot_cdf,
    print_headline,
    run_settings,
    write_report,
)
from vgpnav_env.eval.workers import Workers, workers_from_args
from vgpnav_env.perception.pipeline import LOST_REASONS
from vgpnav_env.perception.verify import VERIFY_CHECKS
from vgpnav_env.runs import load_build

#: One scene's evaluation: (metrics incl. ``records``, figures by file name) of a query run, its
#: frames perceived by the given workers.
Evaluate = Callable[[QueryRun, Workers], tuple[dict[str, Any], dict[str, Figure]]]
#: One scene's headline (printed by the command) from the scene name and its metrics.
Headline = Callable[[str, dict[str, Any]], str]


def time_metrics(records: Sequence[FrameRecord]) -> dict[str, float]:
    """Mean and median CPU seconds per frame (process CPU time of ``perceive``, all threads)."""
    cpu = np.array([r.timings.get("cpu", np.nan) for r in records], float)
    cpu = cpu[np.isfinite(cpu)]
    if not len(cpu):
        return {"cpu_s_per_frame": float("nan"), "cpu_s_per_frame_median": float("nan")}
    return {"cpu_s_per_frame": float(cpu.mean()), "cpu_s_per_frame_median": float(np.median(cpu))}


def error_cdf_figure(records: Sequence[FrameRecord], title: str = "") -> Figure:
    """Cumulative fraction of ALL queries (lost never reach 1) below a translation / rotation error;
    dashed lines mark the recall and gross-error thresholds."""
    fig = Figure(figsize=(9, 3.4))
    axes = fig.subplots(1, 2)
    for ax, key, unit, marks in (
        (axes[0], "translation_m", "m", (0.05, 0.25, 0.5)),
        (axes[1], "rotation_deg", "deg", (2.0, 5.0, 10.0)),
    ):
        plot_cdf(ax, [getattr(r, key) for r in records], total=len(records))
        for m in marks:
            ax.axvline(m, color="grey", lw=0.6, ls="--")
        ax.set_xlabel(f"{key.split('_')[0]} error ({unit})")
    axes[0].set_ylabel("fraction of queries")
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def confidence_figure(records: Sequence[FrameRecord], title: str = "") -> Figure:
    """ROC of the per-frame confidence (right pose vs gross error, :func:`confidence_roc`)."""
    fpr, tpr, auc = confidence_roc(list(records))
    fig = Figure(figsize=(4.2, 4.0))
    ax = fig.subplots()
    if len(fpr):
        ax.step(fpr, tpr, where="post", label=f"AUC {auc:.3f}")
        ax.legend(loc="lower right")
    else:
        ax.text(0.5, 0.5, "no gross error (or no right pose) to separate", ha="center", fontsize=8)
    ax.plot([0, 1], [0, 1], color="grey", lw=0.6, ls="--")
    ax.set_xlabel("gross errors accepted (false-positive rate)")
    ax.set_ylabel("right poses accepted (true-positive rate)")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def worst_frames(records: Sequence[FrameRecord], n: int = 6) -> list[FrameRecord]:
    """The ``n`` localized frames farthest off (error relative to the gross-error thresholds)."""
    localized = [r for r in records if r.status == "localized"]
    return sorted(localized, key=lambda r: -max(r.translation_m / 0.5, r.rotation_deg / 10.0))[:n]


def worst_frames_figure(
    build_dir: Path, records: Sequence[FrameRecord], n: int = 6, n_refs: int = 5
) -> Figure:
    """The worst frames (:func:`worst_frames`), one row each: the query, then up to ``n_refs`` of the
    references its pose came from, each titled with its distance / angle to the TRUE query pose (the
    query's title says whether its retrieval missed and whether only the state estimate's prior
    placed it, :attr:`FrameRecord.prior_placed`)."""
    rows = worst_frames(records, n)
    fig = Figure(figsize=(2.0 * (n_refs + 1), 1.75 * max(len(rows), 1)))
    if not rows:
        fig.text(0.5, 0.5, "no localized frame", ha="center")
        return fig
    build = load_build(build_dir)
    axes = np.atleast_2d(fig.subplots(len(rows), n_refs + 1))
    for row, r in zip(axes, rows, strict=True):
        T_true = build.query.poses[r.frame]
        row[0].imshow(build.query.images[r.frame])
        notes = [
            n
            for n, on in (("retrieval missed", not r.retrieval_hit), ("placed by the prior", r.prior_placed))
            if on
        ]
        title = f"q{r.frame}: {r.translation_m:.2f} m / {r.rotation_deg:.0f}°"
        row[0].set_title("\n".join([title, ", ".join(notes)]) if notes else title, fontsize=6)
        for ax, j in zip(row[1:], [*r.references, *([None] * n_refs)], strict=False):
            if j is not None:
                ax.imshow(build.database.images[j])
                dt, dr = pose_errors(build.database.poses[j], T_true)
                ax.set_title(f"ref {j}: {dt:.1f} m / {dr:.0f}°", fontsize=6)
        for ax in row:
            ax.set_axis_off()
    fig.tight_layout()
    return fig


def frame_table(records: Sequence[FrameRecord]) -> str:
    """Per-frame Markdown table (folded): status, errors, Acc / Comp, retrieval, pairs, detail."""
    rows = [
        (
            r.frame,
            r.status + (" (gross)" if r.gross else ""),
            r.reason,
            r.translation_m,
            r.rotation_deg,
            r.acc_m,
            r.comp_m,
            "yes" if r.retrieval_hit else "no",
            r.n_confident_pairs,
            r.candidate_confidence,
            r.timings.get("cpu"),
            r.detail[:80],
        )
        for r in records
    ]
    header = ["frame", "status", "reason", "t (m)", "r (deg)", "Acc (m)", "Comp (m)", "retrieval hit",
              "pairs", "confidence", "CPU s", "detail"]  # fmt: skip
    return (
        "## Per-frame results\n\n<details><summary>all frames</summary>\n\n"
        + markdown_table(header, rows)
        + "\n\n</details>"
    )


def lost_table(metrics: dict[str, Any]) -> str:
    """The lost queries per gate (``lost_by_gate``: the reason, or the verification check that
    rejected the pose) with how far the rejected pose was from the truth."""
    lost = metrics["lost_by_gate"]
    if not lost:
        return "No query was lost."
    rows = [(gate, sum(n.values()), *(n[c] for c in CANDIDATE_CLASSES)) for gate, n in lost.items()]
    classes = "; ".join(f"{c}: {meaning}" for c, meaning in CANDIDATE_CLASSES.items())
    return (
        "## Lost queries by reason\n\nThe gate that rejected each lost query and how far its rejected "
        f"pose was from the true one ({classes}).\n\n"
        + markdown_table(["reason", "count", *CANDIDATE_CLASSES], rows)
    )


#: The gross-error rate a trusted pose may have (issue 8's target): :func:`trust_metrics`.
TRUSTED_GROSS_RATE = 0.01


def trust_metrics(
    records: Sequence[FrameRecord], max_gross_rate: float = TRUSTED_GROSS_RATE
) -> dict[str, float]:
    """What a confidence threshold that makes the poses trustworthy costs, read off the ROC.

    ``trust_confidence``: the lowest threshold on ``confidence`` such that at most
    ``max_gross_rate`` of the localized frames at or above it are gross (:data:`GROSS_ERROR`); 0
    when all localized frames already qualify, inf when no threshold does (the most confident
    pose is gross). ``trust_lost_rate``: the queries lost or below it (of all queries);
    ``trust_recall_5cm_5deg``: the queries kept and within 5 cm / 5 deg (of all queries).
    """
    n = len(records)
    loc = [r for r in records if r.status == "localized"]
    conf = np.array([r.confidence for r in loc], float)
    gross = np.array([bool(is_gross(r.translation_m, r.rotation_deg)) for r in loc], bool)
    threshold = float("inf")
    if len(loc) and gross.sum() <= max_gross_rate * len(loc):
        threshold = 0.0
    else:
        for t in np.unique(conf):  # ascending: the first that qualifies keeps the most frames
            keep = conf >= t
            if gross[keep].sum() <= max_gross_rate * keep.sum():
                threshold = float(t)
                break
    keep = conf >= threshold
    tm, deg = RECALL_THRESHOLDS["recall_5cm_5deg"]
    right = np.array([r.translation_m <= tm and r.rotation_deg <= deg for r in loc], bool)
    return {
        "trust_confidence": threshold,
        "trust_lost_rate": float(1.0 - keep.sum() / n) if n else float("nan"),
        "trust_recall_5cm_5deg": float((keep & right).sum() / n) if n else float("nan"),
    }


def localization_summary(records: Sequence[FrameRecord]) -> dict[str, Any]:
    """:func:`localization_metrics` + :func:`trust_metrics` + :func:`time_metrics`: the numbers every
    query report shows."""
    return {**localization_metrics(list(records)), **trust_metrics(records), **time_metrics(records)}


def scene_report(
    out: Path,
    title: str,
    scene: str,
    run: QueryRun,
    metrics: dict[str, Any],
    sections: Sequence[str],
    figures: dict[str, Figure],
    run_info: dict[str, Any] | None = None,
) -> None:
    """Write one scene's report: settings (``run_info``: where it ran, wall and CPU time, see
    :func:`~vgpnav_env.eval.report.run_settings`), metrics (with ``records``), lost reasons, the
    given sections, the per-frame table and the figures plus the error CDF and the worst frames."""
    records = [FrameRecord(**r) for r in metrics["records"]]
    settings = {"scene": scene, **run.settings(), **(run_info or {})}
    figures = {
        **figures,
        "errors.png": error_cdf_figure(
            records, f"{scene}: {run.backbone}, k = {run.config.retrieval.k}, {run.mode} mode"
        ),
        "worst.png": worst_frames_figure(run.build_dir, records),
        "confidence.png": confidence_figure(records, f"{scene}: confidence of the verified poses"),
    }
    parts = [
        lost_table(metrics),
        *sections,
        "Recalls and `retrieval_recall` count every query (a lost one fails); median / mean errors "
        "and `gross_rate` (> 0.5 m or 10 deg) are over localized queries. `worst.png`: the worst "
        "localized frames, each query beside the references its pose came from (titles: distance "
        "and angle to the true query pose). `confidence.png`: ROC of the per-frame confidence of "
        "every verified pose (kept or rejected) as a test of right (not gross) against gross. "
        "`trust_confidence`: the lowest confidence threshold that leaves at most 1 % gross errors "
        "among the localized frames; `trust_lost_rate` / `trust_recall_5cm_5deg`: the lost rate and "
        "recall if frames below it were dropped too (what trusting every pose would cost).",
        frame_table(records),
    ]
    labels = {"localized": "the pipeline returned a verified metric pose"}
    labels |= {f"lost: {reason}": meaning for reason, meaning in LOST_REASONS.items()}
    labels |= {
        f"lost: unverified: {check}": meaning
        for check, meaning in VERIFY_CHECKS.items()
        if check != "ambiguity"
    }
    labels["gross"] = "a localized frame more than {:g} m or {:g} deg off the true pose".format(*GROSS_ERROR)
    write_report(out, f"{title}: {scene}", metrics, parts, figures, settings=settings, labels=labels)


def run_scenes(
    args: argparse.Namespace,
    title: str,
    evaluate: Evaluate,
    columns: Sequence[str],
    headline: Headline,
    sections: Callable[[dict[str, Any]], list[str]] = lambda metrics: [],
    *,
    scale: bool = True,
) -> int:
    """Evaluate every scene of ``args.scene`` (a list) on the workers of ``--workers`` / ``--ray``,
    write the reports (module docstring) and print each scene's headline and report path.

    ``columns``: the metric keys of the table across scenes; ``sections``: extra Markdown of one
    scene's report from its metrics. Arguments are checked and every build resolved before the
    first scene runs."""
    workers = workers_from_args(args)
    scenes = list(args.scene)
    builds = list(args.build) if args.build is not None else [None] * len(scenes)
    if len(builds) != len(scenes):
        raise ValueError(f"--build needs one directory per scene: {len(scenes)} scenes, {len(builds)} builds")
    if len(set(scenes)) != len(scenes):
        raise ValueError(f"a scene is given twice: {' '.join(scenes)}")
    runs = [
        (scene, QueryRun.from_args(args, scale=scale, scene=scene, build=build))
        for scene, build in zip(scenes, builds, strict=True)
    ]
    summary: dict[str, dict[str, Any]] = {}
    total = RunClock()
    with workers:
        for scene, run in runs:
            out = args.out if len(runs) == 1 else args.out / re.sub(r"[^A-Za-z0-9_.-]+", "-", scene)
            clock, cpu0 = RunClock(), workers.cpu_seconds
            metrics, figures = evaluate(run, workers)
            info = run_settings(clock, workers.where, workers.cpu_seconds - cpu0)
            scene_report(out, title, scene, run, metrics, sections(metrics), figures, info)
            summary[scene] = {k: metrics[k] for k in columns} | {"report": str(out / "report.md")}
            print_headline(headline(scene, metrics), out)
    if len(runs) > 1:
        rows = [(scene, *(m[k] for k in columns)) for scene, m in summary.items()]
        table = markdown_table(["scene", *columns], [[_cell(v) for v in row] for row in rows])
        settings = {k: v for k, v in runs[0][1].settings().items() if k != "build"}
        settings |= run_settings(total, workers.where, workers.cpu_seconds)
        parts = [
            "## Scenes\n\n" + table,
            "One report per scene: "
            + ", ".join(f"[{s}]({Path(m['report']).parent.name}/report.md)" for s, m in summary.items()),
        ]
        write_report(args.out, f"{title}: {len(runs)} scenes", {"scenes": summary}, parts, settings=settings)
        print_headline(f"{title}: {len(runs)} scenes side by side", args.out)
    return 0


def _cell(value: Any) -> Any:
    """A table cell: a lost-by-reason dict as ``reason: n, ...``."""
    if isinstance(value, dict):
        return ", ".join(f"{k}: {v}" for k, v in value.items()) or "-"
    return value
