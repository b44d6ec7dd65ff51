"""Fit the calibrated verification model (``vgpnav_env.perception.verify.model``) on logged frames.

Data: the frame records of ``vgpnav eval localization`` reports on the TUNING scenes only
(``vgpnav_env/tasks/splits.yaml``), temporal and paper mode, all query frames (the commands are in
this directory's ``README.md``). Then, from this directory's parent::

    python benchmarks/verification/fit.py collect OUT -o benchmarks/verification/frames.csv
    python benchmarks/verification/fit.py fit benchmarks/verification/frames.csv \\
        -o vgpnav_env/perception/data/verify_model.json

``collect`` keeps every frame whose candidate pose has evidence and an error, mount rejections
included (the model scores every candidate the reports rank; the mount rule still rejects what
it rejects); a row's label is "right" (within 5 cm / 5 deg), its ``split`` the report's perception
split. ``fit`` refuses held-out rows (exit code 2) and is deterministic
(L-BFGS from zero, :func:`~vgpnav_env.perception.verify.model.fit_model`) and prints the training
AUC and, per scene, what the model would accept at ``VerifyConfig.accept_probability`` against
what the rules accepted. ``fit --check MODEL`` refits and exits 1 unless every coefficient agrees
with MODEL's within ``--tolerance``. ``score FRAMES [--model MODEL]`` prints a model's AUC and
decisions on other frames (held-out scenes' records, collected the same way) without fitting.
``scenes FRAMES`` leaves one scene out at a time: the AUC of a fit on the others, per scene.
``fit`` and ``scenes`` take ``--features`` to fit on some of the model's features only, and
``--label not-gross`` to predict that a pose is not gross (0.5 m / 10 deg) instead of right.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

from vgpnav_env.perception.verify import Evidence, VerificationModel, VerifyConfig, default_model, fit_model
from vgpnav_env.perception.verify.model import FEATURES
from vgpnav_env.tasks.splits import perception_split

#: Right: within this (metres, degrees) of the truth, the recall threshold the model predicts.
RIGHT = (0.05, 5.0)
#: The L2 penalty on the standardised coefficients.
L2 = 1.0


def collect(report_dirs: list[Path]) -> list[dict[str, object]]:
    """The rows (scene, split, frame, status, right, gross, features) of every ``report.json`` below
    ``report_dirs``; ``split`` is the report's perception split (tuning or held-out)."""
    rows = []
    for root in report_dirs:
        for path in sorted(Path(root).rglob("report.json")):
            report = json.loads(path.read_text())
            settings = report.get("settings", {})
            source = str(settings.get("scene") or path.parent.name)
            split = settings.get("perception split") or perception_split(source)
            scene = Path(source).name
            for r in report.get("records", []):
                ev = r.get("evidence") or {}
                t, deg = r["candidate_translation_m"], r["candidate_rotation_deg"]
                if not ev or t is None or deg is None:
                    continue
                if not (np.isfinite(t) and np.isfinite(deg)):
                    continue
                right = t <= RIGHT[0] and deg <= RIGHT[1]
                gross = t > 0.5 or deg > 10.0
                row = {"scene": scene, "split": split, "frame": r["frame"], "status": r["status"]}
                row |= {"right": int(right)}
                evidence = Evidence(**ev)
                row |= {"gross": int(gross)} | {f: float(getattr(evidence, f)) for f in FEATURES}
                rows.append(row)
    return rows


def write_rows(path: Path, rows: list[dict[str, object]]) -> None:
    """Write frame rows (:func:`collect`'s) as CSV, the header from the first row."""
    with open(path, "w", newline="") as out:
        writer = csv.DictWriter(out, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def read_rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


#: What a model may predict: "right" (within :data:`RIGHT`, the installed model's) or "not-gross"
#: (within 0.5 m / 10 deg: the reports' confidence AUC ranks not gross against gross).
LABELS = ("right", "not-gross")


def labels(rows: list[dict[str, str]], label: str = "right") -> np.ndarray:
    """(n,) bool: the rows that are positive for ``label`` (one of :data:`LABELS`)."""
    if label not in LABELS:
        raise ValueError(f"label must be one of {LABELS}, got {label!r}")
    if label == "right":
        return np.array([int(r["right"]) for r in rows], bool)
    return np.array([not int(r["gross"]) for r in rows], bool)


def fit(
    rows: list[dict[str, str]], features: tuple[str, ...] = FEATURES, label: str = "right"
) -> VerificationModel:
    """The model of ``features`` (default: the package's) fitted on ``rows`` to predict ``label``."""
    X = np.array([[float(r[f]) for f in features] for r in rows])
    y = labels(rows, label)
    scenes = sorted({r["scene"] for r in rows})
    meta = {"scenes": scenes, "right_m_deg": list(RIGHT)} | ({"label": label} if label != "right" else {})
    return fit_model(X, y, features, l2=L2, meta=meta)


def auc(score: np.ndarray, positive: np.ndarray) -> float:
    """Probability that a positive scores above a negative (ties half); nan when a class is empty."""
    a, b = score[positive][:, None], score[~positive][None, :]
    if a.size == 0 or b.size == 0:
        return float("nan")
    return float(((a > b).sum() + 0.5 * (a == b).sum()) / (a.size * b.size))


def summary(model: VerificationModel, rows: list[dict[str, str]]) -> str:
    X = np.array([[float(r[f]) for f in model.features] for r in rows])
    p = model.probabilities(X)
    right = np.array([int(r["right"]) for r in rows], bool)
    gross = np.array([int(r["gross"]) for r in rows], bool)
    ruled = np.array([r["status"] == "localized" for r in rows], bool)
    accept = p >= VerifyConfig().accept_probability
    lines = [
        f"rows {len(rows)}, right {int(right.sum())}, gross {int(gross.sum())}; "
        f"AUC right vs not {auc(p, right):.3f}, "
        f"right vs gross {auc(p[right | gross], right[right | gross]):.3f}, "
        f"not gross vs gross (the reports' confidence AUC) {auc(p, ~gross):.3f}",
        "| scene | rows | rules: accepted / gross / right | model: accepted / gross / right | reports' AUC |",
        "|---|---|---|---|---|",
    ]
    for scene in sorted({r["scene"] for r in rows}):
        m = np.array([r["scene"] == scene for r in rows])
        cells = [
            f"{int((a & m).sum())} / {int((a & m & gross).sum())} / {int((a & m & right).sum())}"
            for a in (ruled, accept)
        ]
        lines.append(f"| {scene} | {int(m.sum())} | {cells[0]} | {cells[1]} | {auc(p[m], ~gross[m]):.3f} |")
    return "\n".join(lines)


def leave_one_scene_out(
    rows: list[dict[str, str]], features: tuple[str, ...] = FEATURES, label: str = "right"
) -> str:
    """Leave one scene out: per scene, the AUC (right against gross) of the model fitted on the other
    scenes' rows, and the pooled AUC of those out-of-scene probabilities (how well a fit carries to a
    scene it has not seen), for a model of ``features`` predicting ``label``."""
    scenes = sorted({r["scene"] for r in rows})
    X = np.array([[float(r[f]) for f in features] for r in rows])
    right = np.array([int(r["right"]) for r in rows], bool)
    gross = np.array([int(r["gross"]) for r in rows], bool)
    p = np.full(len(rows), np.nan)
    lines = ["| left out | rows | gross | AUC right vs gross |", "|---|---|---|---|"]
    per_scene = []
    for scene in scenes:
        out = np.array([r["scene"] == scene for r in rows])
        kept = [r for r, o in zip(rows, out, strict=True) if not o]
        p[out] = fit(kept, features, label).probabilities(X[out])
        pair = out & (right | gross)
        per_scene.append(auc(p[pair], right[pair]))
        lines.append(f"| {scene} | {int(out.sum())} | {int((out & gross).sum())} | {per_scene[-1]:.3f} |")
    pooled = auc(p[right | gross], right[right | gross])
    mean = float(np.nanmean(per_scene))
    head = f"leave one scene out, pooled AUC right vs gross {pooled:.3f}, mean over scenes {mean:.3f}"
    return "\n".join([head, *lines])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    c = sub.add_parser("collect", help="report directories -> frames CSV")
    c.add_argument("reports", nargs="+", type=Path)
    c.add_argument("-o", "--out", type=Path, required=True)
    f = sub.add_parser("fit", help="frames CSV -> model JSON")
    f.add_argument("frames", type=Path)
    f.add_argument("-o", "--out", type=Path)
    f.add_argument("--check", type=Path, metavar="MODEL", help="compare with MODEL instead of writing")
    f.add_argument("--tolerance", type=float, default=1e-4)
    features = {"nargs": "+", "choices": FEATURES, "default": FEATURES, "metavar": "FEATURE"}
    f.add_argument("--features", **features, help="fit on these features only (ablations)")
    label = {"choices": LABELS, "default": "right", "help": "what the model predicts (default right)"}
    f.add_argument("--label", **label)
    s = sub.add_parser("score", help="a model's AUC and decisions on a frames CSV (e.g. held-out scenes)")
    s.add_argument("frames", type=Path)
    s.add_argument("--model", type=Path, help="model JSON (default: the installed model)")
    v = sub.add_parser("scenes", help="leave one scene out: how a fit carries to an unseen scene")
    v.add_argument("frames", type=Path)
    v.add_argument("--features", **features, help="fit on these features only (ablations)")
    v.add_argument("--label", **label)
    args = parser.parse_args(argv)
    if args.command == "collect":
        rows = collect(args.reports)
        if not rows:
            print("no frames with evidence under the given directories", file=sys.stderr)
            return 2
        write_rows(args.out, rows)
        print(f"{len(rows)} frames -> {args.out}")
        return 0
    rows = read_rows(args.frames)
    if args.command == "scenes":
        if len({r["scene"] for r in rows}) < 2:
            print(f"{args.frames} holds one scene: nothing to leave out", file=sys.stderr)
            return 2
        print(leave_one_scene_out(rows, tuple(args.features), args.label))
        return 0
    if args.command == "score":
        try:
            model = VerificationModel.load(args.model) if args.model is not None else default_model()
        except (OSError, ValueError, KeyError) as error:
            print(f"cannot read the model {args.model}: {error}", file=sys.stderr)
            return 2
        if model is None:
            print("no model: give --model or install one", file=sys.stderr)
            return 2
        print(summary(model, rows))
        return 0
    held_out = sorted({r["scene"] for r in rows if r.get("split") != "tuning"})
    if held_out:
        print(
            f"{args.frames}: rows of scenes not marked tuning {held_out}; "
            "fit only on perception tuning scenes (score held-out frames with `score`)",
            file=sys.stderr,
        )
        return 2
    model = fit(rows, tuple(args.features), args.label)
    print(summary(model, rows))
    if args.check is not None:
        stored = VerificationModel.load(args.check)
        got = np.r_[model.intercept, model.coef]
        want = np.r_[stored.intercept, stored.coef]
        worst = float(np.abs(got - want).max())
        print(f"largest coefficient difference {worst:.2e} (tolerance {args.tolerance:g})")
        return 0 if worst <= args.tolerance and model.features == stored.features else 1
    if args.out is not None:
        model.save(args.out)
        print(f"model -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
