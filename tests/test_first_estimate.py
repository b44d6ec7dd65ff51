"""A temporal run whose first frames are lost, and whose ground anchor therefore fails, still gets
its first estimate later, also when the map's floor (the database reconstruction's) is wrong:
a small version of a corpus run whose state estimate never started, every right pose that could
anchor the ground rejected by the camera-height check against a wrong floor."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_pipeline import FAST_VLAD
from tiny_build import QUERY_HEIGHT

from vgpnav_env.geometry import camera_yaw_pitch, wrap_angle
from vgpnav_env.perception.database import Database, DatabaseConfig
from vgpnav_env.perception.pipeline import Perceiver, PerceptionConfig
from vgpnav_env.perception.state import EKFState
from vgpnav_env.robot import base_pose, camera_T_wc
from vgpnav_env.runs import load_run


@pytest.fixture(scope="module")
def database(tiny_build_dir: Path) -> Database:
    return Database.open(tiny_build_dir, config=DatabaseConfig(vlad=FAST_VLAD, prior_stride=3))


def _odometry(previous: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """The true planar motion (forward, left, yaw) from ``previous`` to ``pose`` in ``previous``'s frame."""
    c, s = np.cos(previous[2]), np.sin(previous[2])
    dx, dy = pose[:2] - previous[:2]
    return np.array([c * dx + s * dy, -s * dx + c * dy, wrap_angle(pose[2] - previous[2])])


@pytest.mark.parametrize("wrong", [None, "map floor", "anchor"])
def test_lost_first_frames_and_a_failed_anchor_still_give_a_first_estimate(
    database: Database, tiny_build_dir: Path, wrong: str | None, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``wrong``: nothing; the map's floor (truly at z = 0) 0.4 m too high; or the ground anchored
    1 m too low by the first frame (as a wrong first pose would)."""
    if wrong == "map floor":
        monkeypatch.setattr(database, "z_ground", 0.4)
    run = load_run(tiny_build_dir / "query")
    dark = np.zeros_like(run.images[0])  # nothing to match: lost
    order = [0, 1, 4, 3, 2, 5]
    frames = [(dark, run.poses[0])] * 3 + [(run.images[i], run.poses[i]) for i in order]
    truth = np.array([base_pose(T) for _, T in frames])
    pitch = camera_yaw_pitch(run.poses[0])[1]
    perceiver = Perceiver(database, "classical", config=PerceptionConfig(camera_height=QUERY_HEIGHT))
    if wrong == "anchor":
        assert perceiver.initialize(run.images[0])[0].localized
        perceiver.anchor.z_ground -= 1.0
        frames = frames[3:]
        truth = truth[3:]
    else:
        initial = perceiver.initialize(dark)
        assert not initial[0].localized and not perceiver.initialized  # the ground anchor failed
    ekf = EKFState([-2.0, -2.0, -np.pi], [6.0, 7.0, np.pi])
    ekf.reset(dark, fallback=[2.0, 2.5, 0.0])
    first = None
    for n, (rgb, _) in enumerate(frames):
        if n:
            motion = _odometry(truth[n - 1], truth[n])
            ekf.predict_odometry(motion, ekf.odometry_covariance(motion) + np.diag([1e-4, 1e-4, 1e-4]))
        predicted = ekf.tracking_pose()
        T_pred = None if predicted is None else camera_T_wc(predicted, QUERY_HEIGHT, pitch)
        result = perceiver.perceive(rgb, predicted=T_pred, prior=ekf.prior())
        if n < 3 and wrong != "anchor":
            assert result.status == "lost"
        measured = result.measurement
        ekf.correct(None if measured is None else base_pose(measured), result.confidence)
        if ekf.has_estimate and first is None:
            first = n
    assert perceiver.initialized  # a later verified pose anchored the ground
    assert first is not None and (first >= 3 or wrong == "anchor"), "the state estimate never started"
    assert np.linalg.norm(ekf.estimate[:2] - truth[-1, :2]) < 0.1
