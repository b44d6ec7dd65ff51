"""Navigation protocol: report contents, trajectory pictures, CLI and failure classification."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from vgpnav_env.eval.navigation import (
    EpisodeRecord,
    classify_failure,
    evaluate_navigation,
    plan_agent,
    summarize,
)


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


def test_progress_shows_the_running_episodes_step_and_changes_nothing(tmp_path, capsys):
    kwargs = {"agent": "oracle", "episodes": 2, "seed": 5, "size": (64, 48)}
    quiet = evaluate_navigation("home", progress=False, **kwargs)
    assert capsys.readouterr().err == ""
    shown = evaluate_navigation("home", progress=True, **kwargs)
    err = capsys.readouterr().err
    assert shown["records"] == quiet["records"]
    for r in quiet["records"]:  # every step of every episode was shown, up to its last
        for n in (1, r["steps"]):
            assert re.search(rf"episode {r['index']}: step {n}\b", err), (n, err[-500:])
    assert "navigation home oracle" in err and "2/2" in err


SETTINGS = (
    "scene",
    "layout",
    "image size",
    "backbone",
    "perception mode",
    "max steps",
    "success radius (m)",
    "seeds",
    "wall time (s)",
    "CPU (s)",
    "package version",
)


def test_cli_prints_headline_writes_settings_first_and_runs_compare_side_by_side(tmp_path, capsys):
    from vgpnav_env.cli import main

    outs = [tmp_path / "seed0", tmp_path / "seed4"]
    for out, seed in zip(outs, ("0", "4"), strict=True):
        argv = ["eval", "navigation", "home", "--agent", "oracle", "--episodes", "2", "--size", "64x48",
                "--max-steps", "300", "--seed", seed, "--workers", "1", "--out", str(out)]  # fmt: skip
        assert main(argv) == 0
        lines = capsys.readouterr().out.strip().splitlines()
        assert lines[0].startswith("navigation home (oracle): success ") and "SPL" in lines[0]
        assert lines[-1] == f"report: {out / 'report.md'}"
        saved = json.loads((out / "report.json").read_text())
        assert saved["episodes"] == 2 and set(SETTINGS) <= set(saved["settings"])
        assert (
            saved["settings"]["max steps"] == 300 and saved["settings"]["seeds"] == f"{seed}-{int(seed) + 1}"
        )
        assert saved["settings"]["CPU (s)"] > 0 and set(saved["labels"]) == {
            "lost", "mislocalized", "stopped-too-far", "timeout"}  # fmt: skip
        md = (out / "report.md").read_text()
        assert md.index("## Settings") < md.index("## Labels") < md.index("success_rate")
        assert "| max steps | 300 |" in md and "| success radius (m) | 0.5 |" in md
    assert main(["report", *map(str, outs), "--out", str(tmp_path / "both")]) == 0
    assert capsys.readouterr().out.strip().endswith(f"report: {tmp_path / 'both' / 'report.md'}")
    md = (tmp_path / "both" / "report.md").read_text()
    assert "|  | seed0 | seed4 |" in md and "| success_rate |" in md and "| seeds | 0-1 | 4-5 |" in md
    assert (tmp_path / "both" / "comparison.png").stat().st_size > 5000


def test_bad_agent_names_are_rejected(tmp_path, capsys):
    from vgpnav_env.cli import main

    with pytest.raises(ValueError, match="allowed: astar, oracle, ppo:PATH"):
        plan_agent("greedy", "classical")
    with pytest.raises(FileNotFoundError):
        plan_agent(f"ppo:{tmp_path / 'missing'}", "classical")
    for agent, message in (
        ("greedy", "unknown agent"),
        ("ppo:/missing.zip", "no PPO model"),
        ("ppo", "needs a path"),
    ):
        out = tmp_path / "x"
        with pytest.raises(SystemExit) as e:
            main(["eval", "navigation", "home", "--agent", agent, "--out", str(out)])
        err = capsys.readouterr().err.strip().splitlines()
        assert e.value.code == 2 and len(err) == 1 and message in err[0], err
        assert not out.exists()


def _record(
    success: bool, failure: str | None, loc: float | None = None, frames: dict | None = None
) -> EpisodeRecord:
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
        frames=frames or {},
    )


def test_summary_aggregates_and_counts_failures():
    frames = {"localization_error_m": [0.0] * 19 + [1.0], "localized": [True] * 20}
    s = summarize(
        [_record(True, None, 0.1, frames), _record(False, "timeout", 0.3, frames), _record(False, "lost")]
    )
    assert s["success_rate"] == pytest.approx(1 / 3) and s["spl"] == pytest.approx(0.8 / 3)
    assert s["mean_localization_error_m"] == pytest.approx(0.2)
    # 95th percentile over all 40 frames (two of them 1.0 m off), not over episodes.
    assert s["p95_localization_error_m"] == pytest.approx(np.percentile([0.0] * 38 + [1.0] * 2, 95))
    assert s["failures"] == {"lost": 1, "mislocalized": 0, "stopped-too-far": 0, "timeout": 1}
    assert s["collisions_per_episode"] == 1.0 and np.isfinite(s["soft_spl"])
    # Frames without a pose estimate (nan: before the first fix) are left out of the percentile.
    before = {"localization_error_m": [float("nan")] * 20 + [0.0] * 19 + [1.0]}
    p95 = summarize([_record(True, None, 0.1, before)])["p95_localization_error_m"]
    assert p95 == pytest.approx(np.percentile([0.0] * 19 + [1.0], 95))
    assert list(s) == [
        "episodes",
        "success_rate",
        "spl",
        "soft_spl",
        "collisions_per_episode",
        "mean_steps",
        "mean_localization_error_m",
        "p95_localization_error_m",
        "mean_no_estimate_fraction",
        "mean_lost_fraction",
        "mean_tracked_fraction",
        "mean_relocalized_fraction",
        "mean_gross_pose_fraction",
        "mean_map_precision",
        "mean_map_recall",
        "mean_map_iou",
        "mean_path_phantom_cells",
        "failures",
    ]


@pytest.mark.parametrize(
    ("errors", "localized", "stopped", "label"),
    [
        ([0.01] * 10, [False] * 10, False, "lost"),  # never localized
        ([0.01] * 10, [True] + [False] * 9, False, "timeout"),  # lost 90% of frames, pose still right
        ([0.01] * 10, [True] + [False] * 9, True, "stopped-too-far"),
        ([0.01] * 9 + [0.8], [True] * 10, False, "mislocalized"),  # wrong at the end
        ([0.8] * 5 + [0.01] * 5, [True] * 10, True, "mislocalized"),  # wrong on half of the frames
        ([0.8] * 4 + [0.01] * 6, [True] * 10, True, "stopped-too-far"),
        ([], [], False, "timeout"),  # no estimate (the oracle)
    ],
)
def test_failure_labels_say_what_happened(errors, localized, stopped, label):
    frames = {"localization_error_m": errors, "localized": localized} if errors else {}
    assert classify_failure({"success": False}, frames, stopped, success_distance=0.5) == label
    assert classify_failure({"success": True}, frames, stopped, success_distance=0.5) is None


@pytest.mark.slow
def test_astar_with_privileged_perception_reports_localization(home_database, home_build, tmp_path):
    from conftest import HOME_DATABASE_CONFIG, HOME_SIZE

    report = evaluate_navigation(
        "home",
        agent="astar",
        backbone="simulated",
        episodes=1,
        seed=17,  # a short episode (2.7 m): the report's localization fields are the point
        size=HOME_SIZE,
        out_dir=tmp_path / "astar",
        progress=False,
        database_dir=home_build,
        wrapper_kwargs={"database_config": HOME_DATABASE_CONFIG},  # opens home_database
    )
    assert report["backbone"] == "simulated" and report["episodes"] == 1
    assert report["mean_localization_error_m"] < 0.05  # noise-free privileged backbone
    assert report["records"][0]["estimated_trajectory"] is not None
    assert report["success_rate"] == 1.0


def test_summary_figure_marks_whole_episodes():
    from dataclasses import replace

    from vgpnav_env.eval.navigation_plots import summary_figure

    records = [replace(_record(True, None, 0.1), index=i) for i in range(20)]
    fig = summary_figure(records, success_distance=0.5)
    fig.canvas.draw()
    ticks = fig.axes[1].get_xticks()
    assert len(ticks) >= 3 and np.allclose(ticks, np.round(ticks))


def test_estimated_trajectory_leaves_out_frames_before_the_first_estimate():
    from dataclasses import replace
    from types import SimpleNamespace

    from matplotlib.figure import Figure

    from vgpnav_env.eval.navigation_plots import _ground_truth_panel

    shape = (20, 20)
    spec = SimpleNamespace(shape=shape, bounds=((0.0, 0.0), (2.0, 2.0)))
    truth = SimpleNamespace(spec=spec, free=np.ones(shape, bool), obstacle=np.zeros(shape, bool))
    base = SimpleNamespace(ground_truth=truth, world=SimpleNamespace(navigable=np.ones(shape, bool)),
                           success_distance=0.5)  # fmt: skip
    # Two placeholder poses at (9, 9) before the first estimate, then three estimated frames.
    estimated = [[9.0, 9.0, 0.0]] * 2 + [[0.5, 0.5, 0.0], [0.6, 0.5, 0.0], [0.7, 0.5, 0.0]]
    no_estimate, localized = [True, True, False, False, False], [False, False, True, False, True]
    frames = {"no_estimate": no_estimate, "localized": localized}
    record = replace(_record(True, None, 0.1, frames), trajectory=[[0.5, 0.5, 0.0]] * 6,
                     estimated_trajectory=estimated)  # fmt: skip
    ax = Figure().subplots()
    _ground_truth_panel(ax, SimpleNamespace(unwrapped=base), record)
    lines = {line.get_label(): line for line in ax.get_lines()}
    assert list(lines["estimated"].get_xdata()) == [0.5, 0.6, 0.7]
    assert list(lines["lost (odometry)"].get_xdata()) == [0.6]
