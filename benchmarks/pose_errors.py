"""Where localized poses lose their accuracy: the errors of a localization run's localized frames,
grouped by how the pose came to be.

    python benchmarks/pose_errors.py REPORT_DIR [REPORT_DIR ...]

Reads every ``report.json`` below the given directories (``vgpnav eval localization`` reports) and
prints, over their localized frames pooled, the median translation and rotation errors and the
recall at 5 cm / 5 deg per group: the metric scale's source (``ground``: the ground peak;
``fallback``: the rays' implied scale), the number of confident reference pairs (1-2, 3-5, 6 or
more), and whether the pose was placed inside the state estimate's prior (``prior_placed``:
accepted on less evidence of the images); then the correlation of the translation and rotation
errors. A group with a low recall is where the next accuracy is.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

import numpy as np

from vgpnav_env.eval.perception_runs import RECALL_THRESHOLDS

#: A frame is right within these (metres, degrees): the reports' recall threshold.
RIGHT = RECALL_THRESHOLDS["recall_5cm_5deg"]


def localized_records(dirs: list[Path]) -> list[dict]:
    """The records of the localized frames of every report below ``dirs``."""
    records = []
    for root in dirs:
        for path in sorted(Path(root).rglob("report.json")):
            report = json.loads(path.read_text())
            records += [r for r in report.get("records", []) if r.get("status") == "localized"]
    return records


def table(records: list[dict], name: str, group: Callable[[dict], object]) -> str:
    """A markdown table of ``records``' errors per value of ``group``."""
    groups: dict[str, list[dict]] = defaultdict(list)
    for r in records:
        groups[str(group(r))].append(r)
    lines = [f"| {name} | frames | median error | recall 5 cm / 5 deg |", "| --- | --- | --- | --- |"]
    for key in sorted(groups):
        t = np.array([r["translation_m"] for r in groups[key]])
        deg = np.array([r["rotation_deg"] for r in groups[key]])
        recall = np.mean((t <= RIGHT[0]) & (deg <= RIGHT[1]))
        lines.append(f"| {key} | {len(t)} | {np.median(t):.3f} m / {np.median(deg):.2f} deg | {recall:.2f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("reports", nargs="+", type=Path)
    args = parser.parse_args()
    records = localized_records(args.reports)
    print(f"{len(records)} localized frames\n")
    for name, group in (
        ("scale source", lambda r: r["scale_source"]),
        (
            "confident pairs",
            lambda r: (
                "1-2" if r["n_confident_pairs"] <= 2 else "3-5" if r["n_confident_pairs"] <= 5 else ">= 6"
            ),
        ),
        ("prior placed", lambda r: r["prior_placed"]),
    ):
        print(table(records, name, group) + "\n")
    t = [r["translation_m"] for r in records]
    deg = [r["rotation_deg"] for r in records]
    print(f"correlation of the translation and rotation errors: {np.corrcoef(t, deg)[0, 1]:.2f}")


if __name__ == "__main__":
    main()
