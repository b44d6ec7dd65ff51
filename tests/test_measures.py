"""Measures: the registry, dependency order, the metric values, and a new measure in every report."""

from __future__ import annotations

import json

import numpy as np
import pytest

from vgpnav_env.envs.episodes import Episode
from vgpnav_env.measures import (
    MEASURES,
    EnvState,
    EstimateState,
    Measure,
    Measurements,
    register_measure,
)

EPISODE = Episode(start=(0.0, 0.0, 0.0), goal=(2.0, 0.0), geodesic=2.0)


def euclid(xy) -> float:
    return float(np.hypot(xy[0] - 2.0, xy[1]))


def state(pose, previous=None, action=None, stopped=False, blocked=False) -> EnvState:
    prev = None if previous is None else np.asarray(previous, float)
    return EnvState(EPISODE, np.asarray(pose, float), prev, euclid, 0.5, action, stopped, blocked)


def test_registry_holds_the_habitat_measures_in_info_order():
    assert list(MEASURES)[:8] == [
        "distance_to_goal",
        "euclidean_distance_to_goal",
        "success",
        "spl",
        "soft_spl",
        "collisions",
        "steps",
        "travelled",
    ]
    assert {"localization_error_m", "localized"} <= set(MEASURES)
    with pytest.raises(ValueError, match="already registered"):
        register_measure(MEASURES["spl"])
    with pytest.raises(ValueError, match="no measures"):
        Measurements("nowhere")


def test_env_measures_follow_an_episode():
    m = Measurements("env")
    m.reset(state((0.0, 0.0, 0.0)))
    assert m.metrics() == {
        "distance_to_goal": 2.0,
        "euclidean_distance_to_goal": 2.0,
        "success": False,
        "spl": 0.0,
        "soft_spl": 0.0,
        "collisions": 0,
        "steps": 0,
        "travelled": 0.0,
    }
    path = [(0.5, 0.0), (0.5, 0.0), (1.0, 0.8), (1.6, 0.0)]  # one blocked step, a detour
    previous = (0.0, 0.0)
    for xy in path:
        m.update(state((*xy, 0.0), (*previous, 0.0), 1, blocked=xy == previous))
        previous = xy
    m.update(state((*previous, 0.0), (*previous, 0.0), 0, stopped=True))
    travelled = 0.5 + 0.0 + np.hypot(0.5, 0.8) + np.hypot(0.6, 0.8)
    values = m.metrics()
    assert values["steps"] == 5 and values["collisions"] == 1
    assert values["travelled"] == pytest.approx(travelled)
    assert values["success"] is True and values["distance_to_goal"] == pytest.approx(0.4)
    assert values["spl"] == pytest.approx(2.0 / travelled)
    assert values["soft_spl"] == pytest.approx((1 - 0.4 / 2.0) * 2.0 / travelled)
    m.update(state((0.0, 0.0, 0.0), (1.6, 0.0, 0.0), 0, stopped=True))  # stop too far: no success
    assert m["success"].metric is False and m["spl"].metric == 0.0 and m["soft_spl"].metric == 0.0


def test_estimate_measures_and_episode_values():
    m = Measurements("estimate")
    m.reset(EstimateState(np.array([1.0, 1.0, 0.0], np.float32), True, np.array([1.0, 1.3, 0.0])))
    assert m["localization_error_m"].metric == pytest.approx(0.3) and m["localized"].metric is True
    assert MEASURES["localized"].episode_value([True, True, False, True]) == pytest.approx(0.25)
    assert MEASURES["localization_error_m"].episode_value([0.1, 0.3]) == pytest.approx(0.2)
    assert MEASURES["localization_error_m"].episode_value([]) is None
    assert MEASURES["steps"].episode_value([3, 4]) == 4  # a final-value measure: the last one


def test_frames_without_an_estimate_are_counted_apart_not_as_errors():
    """Before the first fix the pose state has no estimate: its placeholder's error is nan (no
    estimate), not an error; episodes average the errors over the frames with an estimate."""
    m = Measurements("estimate")
    true = np.array([3.0, 0.0, 0.0])
    m.reset(EstimateState(np.zeros(3), False, true, "none", "global", has_estimate=False))
    assert np.isnan(m["localization_error_m"].metric) and np.isnan(m["gross_pose_error"].metric)
    assert m["no_estimate"].metric is True
    m.update(EstimateState(np.array([2.0, 0.0, 0.0]), True, np.array([3.0, 0.0, 0.0]), "reset"))
    assert m["localization_error_m"].metric == 1.0 and m["gross_pose_error"].metric == 1.0
    assert m["no_estimate"].metric is False
    assert MEASURES["localization_error_m"].episode_value([float("nan"), 0.1, 0.3]) == pytest.approx(0.2)
    assert MEASURES["gross_pose_error"].episode_value([float("nan"), 1.0, 0.0]) == pytest.approx(0.5)
    assert MEASURES["localization_error_m"].episode_value([float("nan")]) is None
    assert MEASURES["no_estimate"].episode_value([True, False, False, False]) == pytest.approx(0.25)


def test_dependencies_are_checked():
    class Orphan(Measure):
        uuid = "test_orphan"
        scope = "estimate"
        depends_on = ("success",)  # an env measure: not available to estimate measures

        def update_metric(self, state, measures):
            self.metric = 0

    register_measure(Orphan)
    try:
        with pytest.raises(ValueError, match="depends on 'success'"):
            Measurements("estimate")
    finally:
        del MEASURES["test_orphan"]


@pytest.fixture
def farthest_measure():
    """A new measure defined in one class: the farthest geodesic distance from the goal."""

    class Farthest(Measure):
        uuid = "test_farthest"
        depends_on = ("distance_to_goal",)
        record = "farthest_distance"
        summary = "mean_farthest_distance"
        column = "farthest (m)"

        def reset_metric(self, state, measures):
            self.metric = measures["distance_to_goal"].metric

        def update_metric(self, state, measures):
            self.metric = max(self.metric, measures["distance_to_goal"].metric)

    register_measure(Farthest)
    yield Farthest
    del MEASURES["test_farthest"]


def test_a_new_measure_reaches_info_records_summaries_and_tables(farthest_measure, tmp_path):
    from vgpnav_env.eval.navigation import evaluate_navigation

    out = tmp_path / "nav"
    report = evaluate_navigation(
        "home", agent="oracle", episodes=2, seed=5, size=(64, 48), out_dir=out, progress=False
    )
    saved = json.loads((out / "report.json").read_text())
    for r in saved["records"]:
        assert r["farthest_distance"] >= r["final_distance"] and r["farthest_distance"] > 0
    mean = np.mean([r["farthest_distance"] for r in saved["records"]])
    assert report["mean_farthest_distance"] == pytest.approx(mean)
    assert "| farthest (m) |" in (out / "report.md").read_text()
