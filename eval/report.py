"""Writing benchmark reports: ``DIR/report.json`` plus a Markdown ``DIR/report.md`` with figures.

Every protocol (navigation, localization, perception, timing, ablations) writes through here so
reports look alike and writes are atomic (temp file + rename: a crash never leaves half a report).
A report opens with its settings table (what was run, where, how long: :class:`RunClock`,
:func:`run_settings`), then the definitions of its failure labels, then the metrics; every
``vgpnav eval`` command ends with :func:`print_headline` (its headline numbers and the report path).
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Mapping, Sequence
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import numpy as np

from vgpnav_env.atomic import atomic_write_text

logger = logging.getLogger(__name__)


def _jsonable(value: Any) -> Any:
    """Convert numpy scalars/arrays and paths into JSON types; non-finite floats become None."""
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        return _jsonable(value.item())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    return value


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[Any]], floatfmt: str = ".3f") -> str:
    """A GitHub Markdown table; floats formatted with ``floatfmt``, None shown as '-'."""

    def cell(v: Any) -> str:
        if v is None:
            return "-"
        if isinstance(v, (float, np.floating)):
            return format(float(v), floatfmt) if math.isfinite(v) else "-"
        return str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def package_version() -> str:
    """The installed ``vgpnav-env`` version ("unknown" when run from an uninstalled tree)."""
    try:
        return version("vgpnav-env")
    except PackageNotFoundError:
        return "unknown"


class RunClock:
    """Wall and CPU time of a protocol run, from construction: CPU is this process's
    ``time.process_time`` (all threads) plus what its worker processes report."""

    def __init__(self) -> None:
        self.wall0, self.cpu0 = time.perf_counter(), time.process_time()

    def wall(self) -> float:
        return time.perf_counter() - self.wall0

    def cpu(self, worker_cpu: float = 0.0) -> float:
        return time.process_time() - self.cpu0 + worker_cpu


def run_settings(clock: RunClock, where: str = "this process", worker_cpu: float = 0.0) -> dict[str, Any]:
    """The settings every report ends its table with: where the tasks ran (e.g. ``"2 processes"``),
    wall time, CPU seconds (this process + workers) and the package version."""
    return {
        "workers": where,
        "wall time (s)": round(clock.wall(), 1),
        "CPU (s)": round(clock.cpu(worker_cpu), 1),
        "package version": package_version(),
    }


def settings_table(settings: Mapping[str, Any]) -> str:
    """The ``## Settings`` section: one row per setting (lists and tuples joined)."""

    def value(v: Any) -> Any:
        if isinstance(v, (list, tuple)):
            return ", ".join(map(str, v))
        return format(v, "g") if isinstance(v, float) else v

    return "## Settings\n\n" + markdown_table(
        ["setting", "value"], [(k, value(v)) for k, v in settings.items()]
    )


def write_report(
    out_dir: str | Path,
    title: str,
    metrics: Mapping[str, Any],
    sections: Sequence[str] = (),
    figures: Mapping[str, Any] | None = None,
    *,
    settings: Mapping[str, Any] | None = None,
    labels: Mapping[str, str] | None = None,
) -> Path:
    """Write ``report.json`` (``metrics``, plus ``settings`` and ``labels`` when given) and
    ``report.md``: title, settings table, label definitions, the table of the numeric metrics,
    sections, figures.

    ``labels`` maps each failure or status label the report uses to its definition.
    ``figures`` maps a file name (e.g. ``"errors.png"``) to a matplotlib Figure, saved next to the
    report and linked from the Markdown. Returns the report directory.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    saved = dict(metrics)
    if settings is not None:
        saved["settings"] = dict(settings)
    if labels is not None:
        saved["labels"] = dict(labels)
    atomic_write_text(out / "report.json", json.dumps(_jsonable(saved), indent=2) + "\n")
    scalars = [(k, v) for k, v in metrics.items() if isinstance(v, (int, float, np.number, type(None)))]
    parts = [f"# {title}", ""]
    if settings is not None:
        parts += [settings_table(settings), ""]
    if labels:
        parts += ["## Labels\n", *(f"- `{k}`: {v}" for k, v in labels.items()), ""]
    if scalars:
        parts += [markdown_table(["metric", "value"], scalars), ""]
    parts += [s.rstrip() + "\n" for s in sections]
    for name, fig in (figures or {}).items():
        fig.savefig(out / name, dpi=110, bbox_inches="tight")
        parts.append(f"![{name}]({name})\n")
    atomic_write_text(out / "report.md", "\n".join(parts))
    logger.info("wrote report %s", out / "report.json")
    return out


def print_headline(headline: str, out_dir: str | Path) -> None:
    """The end of every ``vgpnav eval`` command on stdout: its headline numbers and the report path."""
    print(f"{headline}\nreport: {Path(out_dir) / 'report.md'}")


def plot_cdf(ax: Any, values: Any, total: int | None = None, **style: Any) -> None:
    """Cumulative fraction of ``total`` items (default: the values) below each finite value, on a
    log x axis: items without a value (lost frames) keep the curve below 1."""
    v = np.sort(np.asarray(values, float).ravel())
    v = v[np.isfinite(v)]
    n = max(total if total is not None else len(v), 1)
    if len(v):
        ax.step(np.maximum(v, 1e-4), np.arange(1, len(v) + 1) / n, where="post", **style)
        ax.set_xscale("log")
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
