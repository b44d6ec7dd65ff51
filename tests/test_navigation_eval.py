"""Navigation protocol: report contents, trajectory pictures, CLI and failure classification."""

from __future__ import annotations

import json

import numpy as np
import pytest

from vgpnav_env.eval.navigation import EpisodeRecord, evaluate_navigation, make_agent, summarize


def test_oracle_report_json_markdown_and_pictures(tmp_path):
    out = tmp_path / "nav"
    report = evaluate_navigation(
        "home", agent="oracle", episodes=3, seed=5, size=(64, 48), out_dir=out, progress=False
    )
    saved = json.loads((out / "report.json").read_text())
    for key in (
        "success_rate",
        "spl",
        "soft_spl",
        "episodes",
        "collisions_per_episode",
        "mean_localization_error_m",
    ):
        assert key in saved
    assert saved["episodes"] == 3 and len(saved["records"]) == 3
    assert saved["success_rate"] == pytest.approx(report["success_rate"])
    assert [r["seed"] for r in saved["records"]] == [5, 6, 7]
    assert saved["mean_localization_error_m"] is None  # the oracle has no pose estimate
    for r in saved["records"]:
        assert (r["failure"] is None) == r["success"]
        assert 0.0 <= r["spl"] <= 1.0 and len(r["trajectory"]) == r["steps"] + 1
    md = (out / "report.md").read_text()
    assert "success_rate" in md and "trajectories/episode_000.png" in md
    pngs = sorted((out / "trajectories").glob("*.png"))
    assert len(pngs) == 3 and all(p.stat().st_size > 1000 for p in pngs)


def test_cli_eval_navigation_writes_report(tmp_path):
    from vgpnav_env.cli import main

    out = tmp_path / "cli"
    code = main(
        [
            "eval",
            "navigation",
            "home",
            "--agent",
            "oracle",
            "--episodes",
            "2",
            "--size",
            "64x48",
            "--out",
            str(out),
        ]
    )
    assert code == 0
    assert json.loads((out / "report.json").read_text())["episodes"] == 2


def test_bad_agent_names_are_rejected(tmp_path, capsys):
    from vgpnav_env.cli import main

    with pytest.raises(ValueError, match="allowed: astar, oracle, ppo:PATH"):
        make_agent("greedy", "classical")
    with pytest.raises(FileNotFoundError):
        make_agent(f"ppo:{tmp_path / 'missing'}", "classical")
    code = main(["eval", "navigation", "home", "--agent", "greedy", "--out", str(tmp_path / "x")])
    assert code == 2 and "unknown agent" in capsys.readouterr().err


def _record(success: bool, failure: str | None, loc: float | None = None) -> EpisodeRecord:
    metrics = {
        "success": success,
        "spl": 0.8 * success,
        "soft_spl": 0.5,
        "steps": 10,
        "collisions": 1,
        "travelled": 2.5,
        "final_distance": 0.2,
        "final_euclidean_distance": 0.2,
        "localization_error_m": loc,
        "lost_fraction": None,
    }
    return EpisodeRecord(
        index=0,
        seed=0,
        start=[0, 0, 0],
        goal=[1, 1],
        shortest_path_length=2.0,
        failure=failure,
        metrics=metrics,
        trajectory=[],
    )


def test_summary_aggregates_and_counts_failures():
    s = summarize([_record(True, None, 0.1), _record(False, "timeout", 0.3), _record(False, "lost")])
    assert s["success_rate"] == pytest.approx(1 / 3) and s["spl"] == pytest.approx(0.8 / 3)
    assert s["mean_localization_error_m"] == pytest.approx(0.2)
    assert s["failures"] == {"timeout": 1, "stopped-too-far": 0, "lost": 1}
    assert s["collisions_per_episode"] == 1.0 and np.isfinite(s["soft_spl"])
    assert list(s) == [
        "episodes",
        "success_rate",
        "spl",
        "soft_spl",
        "collisions_per_episode",
        "mean_steps",
        "mean_localization_error_m",
        "failures",
    ]


def test_astar_with_privileged_perception_reports_localization(home_build, tmp_path):
    from vgpnav_env.perception.database import DatabaseConfig

    report = evaluate_navigation(
        "home",
        agent="astar",
        backbone="simulated",
        episodes=1,
        seed=7,
        size=(160, 120),
        out_dir=tmp_path / "astar",
        progress=False,
        database_dir=home_build,
        wrapper_kwargs={"database_config": DatabaseConfig(prior="none")},
    )
    assert report["backbone"] == "simulated" and report["episodes"] == 1
    assert report["mean_localization_error_m"] < 0.05  # noise-free privileged backbone
    assert report["records"][0]["estimated_trajectory"] is not None
    assert report["success_rate"] == 1.0
