"""Writing benchmark reports: ``DIR/report.json`` plus a Markdown ``DIR/report.md`` with figures.

Every protocol (navigation, localization, perception, timing, ablations) writes through here so
reports look alike and writes are atomic (temp file + rename: a crash never leaves half a report).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Mapping, Sequence
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


def write_report(
    out_dir: str | Path,
    title: str,
    metrics: Mapping[str, Any],
    sections: Sequence[str] = (),
    figures: Mapping[str, Any] | None = None,
) -> Path:
    """Write ``report.json`` (``metrics``) and ``report.md`` (title, metric table, sections, figures).

    ``figures`` maps a file name (e.g. ``"errors.png"``) to a matplotlib Figure, saved next to the
    report and linked from the Markdown. Returns the report directory.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "report.json", json.dumps(_jsonable(dict(metrics)), indent=2) + "\n")
    scalars = [(k, v) for k, v in metrics.items() if isinstance(v, (int, float, np.number, str, type(None)))]
    parts = [f"# {title}", "", markdown_table(["metric", "value"], scalars), ""]
    parts += [s.rstrip() + "\n" for s in sections]
    for name, fig in (figures or {}).items():
        fig.savefig(out / name, dpi=110, bbox_inches="tight")
        parts.append(f"![{name}]({name})\n")
    atomic_write_text(out / "report.md", "\n".join(parts))
    logger.info("wrote report %s", out / "report.json")
    return out
