"""``vgpnav report DIR [DIR ...] --out OUT``: several evaluation runs side by side.

``vgpnav report DIR [DIR ...] --leaderboard`` prints only the leaderboard rows of the ``vgpnav
bench`` results files among them (the README's benchmark table is this output).

Reads the ``report.json`` every ``vgpnav eval`` and ``vgpnav bench`` command writes and puts the
runs next to each other (e.g. backbones, modes, scenes, agents): one Markdown table of the
settings (one column per run), one of the metrics (every number at the top level of the reports,
and one level into dictionaries such as ``failures`` or ``seconds_per_frame``; per-episode /
per-frame records are left out), ``vgpnav bench`` results also as leaderboard rows, and
``comparison.png`` with one small bar chart per metric that at least two runs have. Writes
``OUT/report.md`` + ``OUT/report.json`` + ``OUT/comparison.png``; a directory without a readable
``report.json`` is refused (exit 2) before anything is written.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from vgpnav_env.eval.report import RunClock, markdown_table, print_headline, run_settings, write_report

#: Report keys that are not metrics (records, structures, the paper's figures).
SKIP = {"records", "settings", "labels", "configs", "table_iv", "table_v", "scenes"}
MAX_PLOTS = 12


def load_report(directory: Path) -> dict[str, Any]:
    """The ``report.json`` of an eval output directory (ValueError in one line when unreadable)."""
    path = Path(directory) / "report.json"
    if not path.is_file():
        raise ValueError(f"{directory}: no report.json (not the --out directory of a vgpnav eval command)")
    try:
        report = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: not a readable report ({e})") from e
    if not isinstance(report, dict):
        raise ValueError(f"{path}: not a vgpnav report (expected a JSON object)")
    return report


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def flat_metrics(report: Mapping[str, Any]) -> dict[str, float]:
    """Numbers of a report: top-level ones and one level into dictionaries (``a.b``); booleans,
    identity fields repeated in its settings (seed, scene, ...) and :data:`SKIP` left out."""
    settings = {k.lower().replace(" ", "_") for k in report.get("settings", {})}
    out: dict[str, float] = {}
    for key, value in report.items():
        if key in SKIP or key.startswith("paper") or key in settings or key == "seed":
            continue
        if _number(value):
            out[key] = float(value)
        elif isinstance(value, Mapping):
            out |= {f"{key}.{k}": float(v) for k, v in value.items() if _number(v)}
    return out


def run_names(directories: Sequence[Path]) -> list[str]:
    """Column names: the shortest distinct path tails (``nav-classical``, ``a/nav`` ...)."""
    parts = [Path(d).resolve().parts for d in directories]
    for depth in range(1, max(len(p) for p in parts) + 1):
        names = ["/".join(p[-depth:]) for p in parts]
        if len(set(names)) == len(names):
            return names
    return [str(d) for d in directories]


def comparison_figure(names: list[str], metrics: list[dict[str, float]]) -> Figure:
    """One bar chart per metric at least two runs have and not all zero (at most :data:`MAX_PLOTS`)."""
    keys = [
        k
        for k in dict.fromkeys(k for m in metrics for k in m)
        if sum(k in m for m in metrics) >= 2 and any(m.get(k) for m in metrics)
    ][:MAX_PLOTS]
    cols = min(4, max(len(keys), 1))
    rows = max(1, math.ceil(len(keys) / cols))
    fig = Figure(figsize=(3.2 * cols, 2.6 * rows + 0.4))
    axes = np.atleast_1d(fig.subplots(rows, cols)).ravel()
    colours = [f"C{i % 10}" for i in range(len(names))]
    for ax, key in zip(axes, keys, strict=False):
        values = [m.get(key, np.nan) for m in metrics]
        ax.bar_label(ax.bar(range(len(names)), values, color=colours), fmt="%.3g", fontsize=6)
        ax.set_title(key, fontsize=8)
        ax.set_xticks(range(len(names)), [str(i + 1) for i in range(len(names))], fontsize=7)
        ax.tick_params(axis="y", labelsize=7)
        ax.grid(axis="y", alpha=0.3)
    for ax in axes[len(keys) :]:
        ax.set_axis_off()
    fig.legend(
        [_swatch(c) for c in colours],
        [f"{i + 1}: {n}" for i, n in enumerate(names)],
        loc="lower center",
        ncol=min(len(names), 4),
        fontsize=7,
        bbox_to_anchor=(0.5, 0.0),
    )
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    return fig


def _swatch(colour: str) -> Any:
    from matplotlib.patches import Patch

    return Patch(color=colour)


def compare(directories: Sequence[Path], out: Path, clock: RunClock | None = None) -> dict[str, Any]:
    """Write the side-by-side report of ``directories`` into ``out``; returns its JSON content."""
    clock = clock or RunClock()
    reports = [load_report(d) for d in directories]
    names = run_names(directories)
    metrics = [flat_metrics(r) for r in reports]
    setting_keys = list(dict.fromkeys(k for r in reports for k in r.get("settings", {})))
    settings_rows = [(k, *(_cell(r.get("settings", {}).get(k)) for r in reports)) for k in setting_keys]
    metric_keys = list(dict.fromkeys(k for m in metrics for k in m))
    metric_rows = [(k, *(m.get(k) for m in metrics)) for k in metric_keys]
    links = ", ".join(
        f"[{n}]({Path(d).resolve() / 'report.md'})" for n, d in zip(names, directories, strict=True)
    )
    header = ["", *names]
    sections = [
        "## Runs\n\n" + links,
        *leaderboard_section(reports),
        "## Settings of the runs\n\n" + markdown_table(header, settings_rows),
        "## Metrics\n\n" + markdown_table(header, metric_rows),
    ]
    content = {
        "runs": [
            {"name": n, "directory": str(Path(d).resolve()), "settings": r.get("settings", {}), "metrics": m}
            for n, d, r, m in zip(names, directories, reports, metrics, strict=True)
        ]
    }
    write_report(
        out,
        f"{len(reports)} runs side by side",
        content,
        sections,
        {"comparison.png": comparison_figure(names, metrics)},
        settings={"runs": len(reports), **run_settings(clock)},
    )
    return content


def leaderboard_table(reports: Sequence[Mapping[str, Any]]) -> str | None:
    """The Markdown leaderboard: one row per ``vgpnav bench`` results file among the reports, in
    their order (None without one)."""
    from vgpnav_env.eval.bench import leaderboard_row
    from vgpnav_env.eval.records import SCHEMA

    rows = [leaderboard_row(dict(r)) for r in reports if r.get("schema") == SCHEMA]
    if not rows:
        return None
    return markdown_table(rows[0][0], [row for _, row in rows])


def leaderboard_section(reports: Sequence[Mapping[str, Any]]) -> list[str]:
    """A ``## Leaderboard`` section of :func:`leaderboard_table` (none without a bench result)."""
    table = leaderboard_table(reports)
    return [] if table is None else ["## Leaderboard\n\n" + table]


def _cell(value: Any) -> Any:
    if isinstance(value, float):
        return format(value, "g")
    return json.dumps(value) if isinstance(value, (dict, list)) else value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("runs", nargs="+", type=Path, metavar="DIR", help="--out directories of vgpnav eval")
    out = parser.add_mutually_exclusive_group(required=True)
    out.add_argument("--out", type=Path, help="directory of the side-by-side report")
    out.add_argument(
        "--leaderboard",
        action="store_true",
        help="print only the leaderboard of the vgpnav bench results files (Markdown), write nothing",
    )


def run(args: argparse.Namespace) -> int:
    clock = RunClock()
    for d in args.runs:
        load_report(d)  # every directory is checked before anything is written
    if len({Path(d).resolve() for d in args.runs}) != len(args.runs):
        raise ValueError("a run directory is given twice")
    if args.leaderboard:
        table = leaderboard_table([load_report(d) for d in args.runs])
        if table is None:
            raise ValueError("--leaderboard: none of the directories holds a vgpnav bench results file")
        print(table)
        return 0
    content = compare(args.runs, args.out, clock)
    shared = set.intersection(*(set(r["metrics"]) for r in content["runs"]))
    print_headline(f"{len(args.runs)} runs side by side, {len(shared)} metrics in common", args.out)
    return 0
