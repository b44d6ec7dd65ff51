"""The calibrated verification model: its fit, its reproduction from the committed script and data,
and its decision."""

from __future__ import annotations

import importlib.util
import json
from dataclasses import fields, replace
from pathlib import Path

import numpy as np
import pytest

from vgpnav_env.perception.verify import Evidence, VerificationModel, VerifyConfig, default_model, fit_model
from vgpnav_env.perception.verify.model import FEATURES

ROOT = Path(__file__).resolve().parents[1]
FIT = ROOT / "benchmarks" / "verification" / "fit.py"
DATA = ROOT / "benchmarks" / "verification" / "frames.csv"
#: The stored coefficients must come back from the script and data to this (the fit is deterministic;
#: the tolerance covers other BLAS / SciPy builds).
TOLERANCE = 1e-3


def _fit_script():
    spec = importlib.util.spec_from_file_location("verification_fit", FIT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_installed_model_reproduces_from_its_script_and_data(capsys: pytest.CaptureFixture) -> None:
    model = default_model()
    assert model is not None and model.features == FEATURES
    stored = ROOT / "vgpnav_env" / "perception" / "data" / "verify_model.json"
    assert _fit_script().main(["fit", str(DATA), "--check", str(stored), "--tolerance", str(TOLERANCE)]) == 0
    assert "largest coefficient difference" in capsys.readouterr().out


def test_score_reports_a_models_auc_on_other_frames(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """``fit.py score`` evaluates a given model on a frames CSV without fitting: on its own training
    data the AUC is the one ``fit`` prints; on the most probable right frame and the least probable
    gross one it is 1."""
    script = _fit_script()
    assert script.main(["score", str(DATA)]) == 0  # the installed model
    installed = capsys.readouterr().out
    assert script.main(["fit", str(DATA)]) == 0
    assert capsys.readouterr().out.splitlines()[0] == installed.splitlines()[0]
    rows = script.read_rows(DATA)
    stored = ROOT / "vgpnav_env" / "perception" / "data" / "verify_model.json"
    model = VerificationModel.load(stored)

    def probability(row: dict[str, str]) -> float:
        return float(model.probabilities(np.array([[float(row[f]) for f in FEATURES]]))[0])

    right = max((r for r in rows if r["right"] == "1"), key=probability)
    gross = min((r for r in rows if r["gross"] == "1"), key=probability)
    two = tmp_path / "two.csv"
    script.write_rows(two, [right, gross])
    assert script.main(["score", str(two), "--model", str(stored)]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first.startswith("rows 2, right 1, gross 1;"), first
    assert "right vs gross 1.000" in first, first
    inverted = tmp_path / "inverted.json"  # --model is the model scored: its opposite ranks them wrong
    replace(model, coef=tuple(-c for c in model.coef), intercept=-model.intercept).save(inverted)
    assert script.main(["score", str(two), "--model", str(inverted)]) == 0
    assert "right vs gross 0.000" in capsys.readouterr().out.splitlines()[0]
    assert script.main(["score", str(two), "--model", str(tmp_path / "missing.json")]) == 2
    assert "cannot read the model" in capsys.readouterr().err


def test_scenes_leaves_each_scene_out(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """``fit.py scenes`` fits on all scenes but one and scores the one left out: one row per scene,
    and a pooled AUC; a CSV of one scene has nothing to leave out (exit code 2)."""
    script = _fit_script()
    rows = script.read_rows(DATA)
    two = [r for r in rows if r["scene"] in ("home", "hospital")]
    path = tmp_path / "two.csv"
    script.write_rows(path, two)
    assert script.main(["scenes", str(path)]) == 0
    out = capsys.readouterr().out.splitlines()
    pooled = float(out[0].rsplit(" ", 1)[1])
    assert out[0].startswith("leave one scene out, pooled AUC right vs gross") and 0.5 < pooled <= 1.0
    assert [line.split(" | ")[0] for line in out[3:]] == ["| home", "| hospital"]
    home = [r for r in two if r["scene"] == "home"]
    script.write_rows(path, home)
    assert script.main(["scenes", str(path)]) == 2
    assert "nothing to leave out" in capsys.readouterr().err


def test_a_not_gross_label_counts_near_poses_as_positive(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """``--label not-gross`` fits on not gross against gross: a near pose (neither right nor gross)
    is a positive there and a negative for the default label; a label outside ``LABELS`` fails."""
    script = _fit_script()
    rows = [r for r in script.read_rows(DATA) if r["scene"] == "home"]
    near = [r for r in rows if r["right"] == "0" and r["gross"] == "0"]
    assert near, "home's rows hold near poses"
    assert not script.labels(near).any() and script.labels(near, "not-gross").all()
    gross = [r for r in rows if r["gross"] == "1"]
    assert not script.labels(gross, "not-gross").any()
    with pytest.raises(ValueError, match="label must be one of"):
        script.labels(rows, "near")
    path, out = tmp_path / "home.csv", tmp_path / "m.json"
    script.write_rows(path, rows)
    assert script.main(["fit", str(path), "--label", "not-gross", "-o", str(out)]) == 0
    assert VerificationModel.load(out).meta["label"] == "not-gross"
    assert script.main(["fit", str(path), "--label", "right", "-o", str(out)]) == 0
    assert "label" not in VerificationModel.load(out).meta
    capsys.readouterr()


def test_fit_recovers_a_known_logistic_model() -> None:
    rng = np.random.default_rng(0)
    X = rng.uniform(0, 1, (4000, 2))
    w = np.array([6.0, -3.0])
    y = rng.uniform(size=4000) < 1 / (1 + np.exp(-(X @ w - 1.5)))
    model = fit_model(X, y, ("a", "b"), l2=1e-6)
    recovered = np.array(model.coef) / np.array(model.scale)  # back to the raw features
    np.testing.assert_allclose(recovered, w, rtol=0.15)
    p = model.probabilities(np.array([[0.9, 0.1], [0.1, 0.9]]))
    assert p[0] > 0.9 and p[1] < 0.1
    with pytest.raises(ValueError, match="right and wrong"):
        fit_model(X, np.ones(4000, bool), ("a", "b"))


def test_the_model_round_trips_through_json(tmp_path: Path) -> None:
    model = fit_model(np.array([[0.0], [1.0], [0.2], [0.8]]), np.array([0, 1, 0, 1], bool), ("a",))
    model.save(tmp_path / "m.json")
    again = VerificationModel.load(tmp_path / "m.json")
    assert again == model


def test_more_explained_evidence_is_more_probably_right() -> None:
    """The installed model ranks a pose that explains most matches, off its planes, with no rival,
    above one that explains few, on one plane, with a rival as strong (both level); it accepts the
    first only (``accept_probability``). A rolled camera lowers the probability."""
    model = default_model()
    good = dict(match_share=0.7, explained_share=0.95, agree_share=0.8, rival_margin=1.0,
                off_plane_share=0.4, confident_rival=0.0, placed=0.0, abs_roll_deg=0.1)  # fmt: skip
    bad = dict(match_share=0.2, explained_share=0.3, agree_share=0.2, rival_margin=0.0,
               off_plane_share=0.02, confident_rival=1.0, placed=0.0, abs_roll_deg=0.1)  # fmt: skip
    p_good, p_bad = model.probabilities(np.array([[good[f] for f in FEATURES], [bad[f] for f in FEATURES]]))
    accept = VerifyConfig().accept_probability
    assert p_good >= accept > p_bad
    rolled = [{**good, "abs_roll_deg": 2.0}[f] for f in FEATURES]
    assert model.probabilities(np.array([rolled]))[0] < accept


def test_fit_refuses_held_out_frames(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """``collect`` marks each row with its report's perception split and ``fit`` refuses rows of a
    held-out scene (exit code 2, nothing written): held-out frames are only ever scored."""
    script = _fit_script()
    rows = script.read_rows(DATA)
    assert {r["split"] for r in rows} == {"tuning"}
    mixed = [*rows[:200], *({**r, "scene": "sh3d_office", "split": "held-out"} for r in rows[200:260])]
    path, model = tmp_path / "mixed.csv", tmp_path / "model.json"
    script.write_rows(path, mixed)
    assert script.main(["fit", str(path), "-o", str(model)]) == 2
    assert "['sh3d_office']" in capsys.readouterr().err and not model.exists()
    assert script.main(["score", str(path)]) == 0  # held-out frames may be scored
    report = tmp_path / "run" / "report.json"
    report.parent.mkdir()
    evidence = {f.name: 0.5 for f in fields(Evidence)} | {"roll_deg": -0.5}
    record = dict(frame=0, status="localized", evidence=evidence, gate="", candidate_translation_m=0.01,
                  candidate_rotation_deg=0.2)  # fmt: skip
    report.write_text(json.dumps({"settings": {"scene": "/data/my_scan"}, "records": [record]}))
    (row,) = script.collect([tmp_path / "run"])
    assert row["scene"] == "my_scan" and row["split"] == "held-out" and row["right"] == 1
    assert row["abs_roll_deg"] == 0.5  # a property of the evidence: the roll either way


def test_fit_and_scenes_take_a_subset_of_the_features(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """``--features`` fits on those features only (the ablations of benchmarks/verification/README.md):
    the written model reads exactly them, and leaving scenes out works with them."""
    script = _fit_script()
    rows = [r for r in script.read_rows(DATA) if r["scene"] in ("home", "hospital")]
    path, model = tmp_path / "two.csv", tmp_path / "m.json"
    script.write_rows(path, rows)
    base = [f for f in FEATURES if f != "abs_roll_deg"]
    assert script.main(["fit", str(path), "--features", *base, "-o", str(model)]) == 0
    assert VerificationModel.load(model).features == tuple(base)
    capsys.readouterr()
    assert script.main(["scenes", str(path), "--features", *base]) == 0
    assert capsys.readouterr().out.startswith("leave one scene out")
    with pytest.raises(SystemExit):
        script.main(["fit", str(path), "--features", "no_such_feature"])
