"""The pose state between frames: dead reckoning, stall detection from pixels, the odometry gate."""

from __future__ import annotations

import numpy as np
import pytest

from vgpnav_env.perception.state import EKFConfig, EKFState, GateConfig, OdometryState
from vgpnav_env.robot import Action

RNG = np.random.default_rng(0)
IMAGES = [RNG.integers(0, 256, (60, 80, 3), dtype=np.uint8) for _ in range(4)]
LOW, HIGH = np.array([-10.0, -10.0, -np.pi]), np.array([10.0, 10.0, np.pi])


def state(**kwargs) -> OdometryState:
    s = OdometryState(LOW, HIGH, **kwargs)
    s.reset(IMAGES[0], fallback=(1.0, 2.0, 0.0))
    return s


def test_no_fix_gives_the_fallback_and_no_gate():
    s = state()
    s.correct(None)
    np.testing.assert_array_equal(s.estimate, (1.0, 2.0, 0.0))
    assert not s.localized
    s.predict(Action.FORWARD, IMAGES[1])
    assert s.gate() is None  # nothing to predict from
    s.correct(None)
    np.testing.assert_array_equal(s.estimate, (1.0, 2.0, 0.0))


def test_dead_reckoning_moves_by_the_motion_model_unless_the_image_stalls():
    s = state()
    s.correct(np.array([0.0, 0.0, 0.0]))
    assert s.localized
    s.predict(Action.FORWARD, IMAGES[1])
    s.correct(None)
    np.testing.assert_allclose(s.estimate, (0.25, 0.0, 0.0))
    assert not s.localized
    s.predict(Action.FORWARD, IMAGES[1])  # the same image again: the step was blocked
    s.correct(None)
    np.testing.assert_allclose(s.estimate, (0.25, 0.0, 0.0))
    s.predict(Action.TURN_LEFT, IMAGES[1])  # turns move even when the view barely changes
    s.correct(None)
    np.testing.assert_allclose(s.estimate, (0.25, 0.0, np.radians(15)))


@pytest.mark.parametrize("kind", [OdometryState, EKFState])
def test_blocked_reports_a_bumped_or_stalled_forward_step_also_before_the_first_fix(kind):
    """The bump sensor decides when there is one; without it (None) an unchanged image does; turns
    are never blocked."""
    s = kind(LOW, HIGH)
    s.reset(IMAGES[0], fallback=(1.0, 2.0, 0.0))
    assert not s.blocked
    s.predict(Action.FORWARD, IMAGES[0])  # no fix yet: the estimate stays the placeholder
    assert s.blocked
    s.predict(Action.FORWARD, IMAGES[1])
    assert not s.blocked
    s.predict(Action.FORWARD, IMAGES[2], bumped=True)  # the image changed, yet the hull touched
    assert s.blocked
    s.predict(Action.FORWARD, IMAGES[2], bumped=False)  # the image did not change: a blank wall
    assert not s.blocked
    s.predict(Action.TURN_LEFT, IMAGES[2])
    assert not s.blocked


def test_gate_is_centred_on_the_prediction_and_grows_with_motion_since_the_fix():
    s = state()
    s.correct(np.array([0.0, 0.0, 0.0]))
    s.predict(Action.FORWARD, IMAGES[1])
    gate = s.gate()
    np.testing.assert_allclose(gate.pose, (0.25, 0.0, 0.0))
    assert gate.max_distance == pytest.approx(0.6) and gate.max_yaw == pytest.approx(np.radians(30))
    s.correct(None)
    s.predict(Action.TURN_RIGHT, IMAGES[2])
    gate = s.gate()
    assert gate.max_distance == pytest.approx(0.6) and gate.max_yaw == pytest.approx(np.radians(35))
    s.correct(np.array([0.3, 0.1, -0.2]))  # a fix: the gate shrinks back
    s.predict(Action.STOP, IMAGES[3])
    gate = s.gate()
    assert gate.max_distance == pytest.approx(0.5) and gate.max_yaw == pytest.approx(np.radians(30))
    assert state(gate=None).gate() is None
    with pytest.raises(ValueError, match="positive"):
        GateConfig(max_distance=0.0)


def test_continuous_actions_keep_the_estimate_and_estimates_stay_in_bounds():
    s = state(discrete=False)
    s.correct(np.array([20.0, -3.0, 0.5]))
    np.testing.assert_array_equal(s.estimate, (10.0, -3.0, 0.5))  # clipped to [LOW, HIGH]
    s.predict(np.array([1.0, 0.0, -1.0]), IMAGES[1])
    assert s.gate() is None
    s.correct(None)
    np.testing.assert_array_equal(s.estimate, (10.0, -3.0, 0.5))
    with pytest.raises(ValueError, match="stall_threshold"):
        state(stall_threshold=-1.0)


# -- the EKF (temporal mode) ------------------------------------------------------------------


def ekf(**kwargs) -> EKFState:
    s = EKFState(LOW, HIGH, **kwargs)
    s.reset(IMAGES[0], fallback=(1.0, 2.0, 0.0))
    return s


def started(**kwargs) -> EKFState:
    """An EKF whose first estimate (0, 0, 0) was started by a strong fix after a weaker one."""
    s = ekf(**kwargs)
    s.correct(np.array([0.0, 0.0, 0.0]))
    s.correct(np.array([0.0, 0.0, 0.0]), score=s.config.init_score)
    assert s.fix == "reset" and s.has_estimate
    return s


def drive(s: EKFState, actions, fixes=None) -> None:
    """Predict and correct along ``actions``, the images changing every step (nothing blocked)."""
    fixes = fixes or [None] * len(actions)
    for n, (action, fix) in enumerate(zip(actions, fixes, strict=True)):
        s.predict(action, IMAGES[1 + n % 3])
        s.correct(fix)


def turn_left_with_fixes(s: EKFState, yaw: float, xy, images) -> tuple[list[str], float]:
    """Turn left 15 deg once per image of ``images``, each turn fixed at ``xy`` with the turned yaw:
    the fix outcomes and the last yaw."""
    outcomes = []
    for image in images:
        yaw += np.radians(15)
        s.predict(Action.TURN_LEFT, image)
        s.correct(np.array([*xy, yaw]))
        outcomes.append(s.fix)
    return outcomes, yaw


def test_ekf_starts_from_a_fix_confirmed_from_another_view():
    """No estimate until ``init_fixes`` (2) fixes agree under the odometry, one of them perceived
    at least 30 deg of turning (or 0.25 m of travel) earlier: a lone wrong first fix (an aliased
    place) does not start the episode there, nor do consistent fixes of one view (an aliased view
    repeats its error); the next view's does."""
    s = ekf()
    s.correct(None)
    np.testing.assert_array_equal(s.estimate, (1.0, 2.0, 0.0))
    assert s.tracking_pose() is None and s.fix == "none"  # no fix yet: relocalize globally
    assert not s.has_estimate
    s.correct(np.array([6.0, -3.0, 1.0]))  # wrong
    assert s.fix == "unconfirmed" and not s.localized and not s.has_estimate
    s.predict(Action.TURN_LEFT, IMAGES[1])
    s.correct(np.array([0.0, 0.0, 0.0]))  # right, but disagrees with the candidate
    assert s.fix == "unconfirmed" and not s.has_estimate
    s.predict(Action.TURN_LEFT, IMAGES[2])
    s.correct(np.array([0.01, 0.0, np.radians(15)]))  # consistent, but only 15 deg turned: one view
    assert s.fix == "unconfirmed" and not s.has_estimate
    s.predict(Action.TURN_LEFT, IMAGES[1])
    s.correct(np.array([0.0, 0.01, np.radians(30)]))  # 30 deg after the right one: confirmed
    assert s.fix == "reset" and s.localized and s.has_estimate
    np.testing.assert_allclose(s.estimate, (0.0, 0.01, np.radians(30)))


def test_ekf_first_estimate_by_travel_or_a_strong_fix():
    """Fixes standing still (the views at reset) never confirm each other; one 0.25 m step later
    a consistent fix does; a fix whose verifier score reaches ``init_score`` starts alone."""
    s = ekf()
    for _ in range(3):
        s.correct(np.array([0.0, 0.0, 0.0]), score=0.8)
        assert s.fix == "unconfirmed"
    s.predict(Action.FORWARD, IMAGES[1])
    s.correct(np.array([0.27, 0.0, 0.0]))
    assert s.fix == "reset"
    np.testing.assert_allclose(s.estimate, (0.27, 0.0, 0.0))
    s = ekf()
    s.correct(np.array([2.0, 1.0, 0.5]), score=0.9)
    assert s.fix == "reset" and s.has_estimate


def test_ekf_tracks_by_odometry_with_growing_covariance():
    s = started()
    np.testing.assert_allclose(s.covariance, s.config.fix_covariance)
    drive(s, [Action.FORWARD] * 4 + [Action.TURN_LEFT])
    np.testing.assert_allclose(s.estimate, (1.0, 0.0, np.radians(15)), atol=1e-9)
    assert s.fix == "none" and not s.localized
    P = s.covariance
    cfg = s.config
    # Along-track variance: the fix's plus 4 forward steps'; the cross-track one also grows with
    # the heading uncertainty (4 x 0.25 m lever arm); the yaw's with one turn.
    assert P[0, 0] == pytest.approx(cfg.fix_sigma**2 + 4 * cfg.forward_sigma**2)
    assert P[1, 1] > cfg.fix_sigma**2 + 4 * cfg.lateral_sigma**2
    assert P[2, 2] == pytest.approx(np.radians(cfg.fix_sigma_deg) ** 2 + np.radians(cfg.turn_sigma_deg) ** 2)
    np.testing.assert_allclose(s.tracking_pose(), s.estimate)


def test_ekf_fix_within_the_gate_corrects_and_shrinks_the_covariance():
    s = started()
    drive(s, [Action.FORWARD] * 4)
    before = s.covariance
    s.predict(Action.FORWARD, IMAGES[2])
    s.correct(np.array([1.3, 0.05, 0.02]))  # 5 cm off the prediction (1.25, 0, 0)
    assert s.fix == "accepted" and s.localized
    assert 1.25 < s.estimate[0] < 1.3 and 0 < s.estimate[1] < 0.05
    assert np.trace(s.covariance[:2, :2]) < np.trace(before[:2, :2])


def test_ekf_blocked_forward_step_moves_nothing():
    s = started()
    s.predict(Action.FORWARD, IMAGES[0])  # the same image, no bump sensor: blocked
    s.correct(None)
    np.testing.assert_allclose(s.estimate, (0.0, 0.0, 0.0))
    s.predict(Action.FORWARD, IMAGES[0], bumped=True)  # bumped, the same image: a push
    s.correct(None)
    np.testing.assert_allclose(s.estimate, (0.0, 0.0, 0.0))
    s.predict(Action.FORWARD, IMAGES[0], bumped=False)  # not bumped: a full step, whatever the image
    s.correct(None)
    np.testing.assert_allclose(s.estimate, (0.25, 0.0, 0.0))


def test_ekf_bumped_step_covers_any_stop_along_the_step():
    """A forward step that bumped while its image changed stopped anywhere along the step (the
    env stops a blocked motion at its last free pose): half a step, the along-track variance of a
    uniform over the step (0.25^2 / 12) added, so that right fixes where the robot stayed and where
    it went a full step are both accepted."""
    for moved in (0.0, 0.125, 0.25):
        s = started()
        s.predict(Action.FORWARD, IMAGES[1], bumped=True)
        np.testing.assert_allclose(s.estimate, (0.125, 0.0, 0.0))
        cfg = s.config
        assert s.covariance[0, 0] == pytest.approx(cfg.fix_sigma**2 + cfg.forward_sigma**2 + 0.25**2 / 12)
        s.correct(np.array([moved, 0.0, 0.0]))
        assert s.fix == "accepted", moved
        assert abs(s.estimate[0] - moved) < 0.05


def test_ekf_rejects_a_gross_fix_and_relocalizes_after_repeated_consistent_ones():
    """A teleport (kidnapping): fixes 3 m away, consistent with each other under the odometry,
    are rejected until they outnumber the estimate's support (4 fixes: the 2 that started it and
    2 accepted since); the fifth relocalizes."""
    s = started()
    drive(s, [Action.FORWARD] * 2, [np.array([0.25, 0.0, 0.0]), np.array([0.5, 0.0, 0.0])])
    far = np.array([0.5, 3.0, 0.0])  # the robot now stands here
    outcomes = []
    for n in range(6):
        s.predict(Action.FORWARD, IMAGES[1 + n % 3])
        far = far + np.array([0.25, 0.0, 0.0])
        s.correct(far)
        outcomes.append(s.fix)
    assert outcomes == ["rejected"] * 4 + ["reset", "accepted"]
    np.testing.assert_allclose(s.estimate[:2], far[:2], atol=0.01)


def test_ekf_keeps_a_well_supported_estimate_against_an_aliased_place():
    """An aliased place (views 1 m to the side of the true pose): after 10 accepted
    fixes, runs of 3 consistent wrong fixes with a right one between them never relocalize, and a
    kidnapping still does once its fixes outnumber the estimate's support (capped at 8)."""
    s = started()
    right = np.zeros(3)
    drive(s, [Action.TURN_LEFT] * 10, [right + [0, 0, np.radians(15) * (n + 1)] for n in range(10)])
    yaw = np.radians(150)
    for _ in range(5):
        for _ in range(3):
            yaw += np.radians(15)
            s.predict(Action.TURN_LEFT, IMAGES[1])
            s.correct(np.array([0.0, 1.0, yaw]))
            assert s.fix == "rejected"
        yaw += np.radians(15)
        s.predict(Action.TURN_LEFT, IMAGES[2])
        s.correct(np.array([0.0, 0.0, yaw]))
        assert s.fix == "accepted"
    outcomes, _ = turn_left_with_fixes(s, yaw, (0.0, 1.0), [IMAGES[1 + n % 3] for n in range(10)])
    assert outcomes == ["rejected"] * 8 + ["reset", "accepted"]


def test_ekf_keeps_its_estimate_against_consistent_wrong_fixes_of_one_spot():
    """Turning in place before and after a bumped push into a wall, the images verify one wrong pose
    again and again, 0.44 m ahead along the view and 10 deg off; three consistent ones within
    ``drift_m`` would reset the estimate there. Fixes of the spot the robot stands on, turned less
    than ``init_view_deg`` net (a blocked step moved nothing for sure), are one view: they do not
    relocalize, and the estimate stays within the half step the bump may have moved. (Turning to and
    fro there longer, the yaw variance grows by each turn's and the fourth pair of turns lets a
    wrong fix through the Mahalanobis gate: not covered.)"""
    s = started()
    yaws = [np.radians(15) * (n + 1) for n in range(8)]
    drive(s, [Action.TURN_LEFT] * 8, [np.array([0.0, 0.0, yaw]) for yaw in yaws])
    yaw = yaws[-1]

    def wrong(yaw: float) -> np.ndarray:
        return np.array([0.44 * np.cos(yaw), 0.44 * np.sin(yaw), yaw + np.radians(10)])

    turn = {Action.TURN_LEFT: np.radians(15), Action.TURN_RIGHT: -np.radians(15)}
    steps = [(Action.TURN_LEFT, True), (Action.TURN_LEFT, False), (Action.FORWARD, False)]
    steps += [(Action.TURN_RIGHT, True), (Action.TURN_RIGHT, True), (Action.TURN_LEFT, True)]
    steps += [(Action.TURN_LEFT, True), (Action.TURN_RIGHT, True)] * 2
    outcomes = []
    for n, (action, seen) in enumerate(steps):
        s.predict(action, IMAGES[1 + n % 3], bumped=action == Action.FORWARD)
        yaw += turn.get(action, 0.0)
        s.correct(wrong(yaw) if seen else None)
        outcomes.append(s.fix)
        assert np.linalg.norm(s.estimate[:2]) < 0.13 and abs(s.estimate[2] - yaw) < np.radians(0.5)
    assert outcomes == ["rejected", "none", "none"] + ["rejected"] * 7
    # Once the robot drives a step, the consistent fixes are another view's: a drifted estimate
    # (here the wrong place is taken to be the right one) is recaptured.
    s.predict(Action.FORWARD, IMAGES[1], bumped=False)
    s.correct(wrong(yaw) + [0.25 * np.cos(yaw), 0.25 * np.sin(yaw), 0.0])
    assert s.fix == "reset"


def test_ekf_inconsistent_outliers_never_relocalize():
    s = started()
    rng = np.random.default_rng(1)
    for n in range(6):  # wrong fixes scattered metres apart: each one starts a new candidate
        s.predict(Action.TURN_LEFT, IMAGES[1 + n % 3])
        s.correct(np.array([*rng.uniform(2.0, 8.0, 2), 0.0]))
        assert s.fix == "rejected"
    np.testing.assert_allclose(s.estimate[:2], (0.0, 0.0), atol=1e-9)


def test_ekf_bridges_a_textureless_stretch_and_takes_the_next_fix():
    """20 forward steps without a fix (a textureless corridor): the estimate follows the odometry,
    the covariance grows (yet stays within tracking: a lost tracked frame hands the next one to
    global retrieval, then tracking resumes, alternating), and a fix 0.3 m off -- the drift a real
    robot accumulates there -- passes the widened gate."""
    s = started()
    tracked = []
    for n in range(20):
        s.predict(Action.FORWARD, IMAGES[1 + n % 3])
        tracked.append(s.tracking_pose() is not None)
        s.correct(None)
    assert tracked == [True, False] * 10
    np.testing.assert_allclose(s.estimate, (5.0, 0.0, 0.0), atol=1e-9)
    s.predict(Action.FORWARD, IMAGES[1])
    assert s.tracking_pose() is not None
    s.correct(np.array([5.25 - 0.3, 0.1, 0.0]))
    assert s.fix == "accepted"


def test_ekf_hands_over_to_global_retrieval_when_uncertain():
    s = started(config=EKFConfig(track_max_sigma=0.2))
    n, tracking = 0, True
    while tracking:  # (tracking_pose decides after each motion update)
        s.predict(Action.FORWARD, IMAGES[1 + n % 3])
        n += 1
        tracking = s.tracking_pose() is not None
    # The cross-track sigma grows fastest (the fix's 2 deg heading sigma times the distance driven,
    # plus 1.5 cm per step): it passes 0.2 m after 21 steps of 0.25 m.
    assert n == 21
    sigma = np.sqrt(np.linalg.eigvalsh(s.covariance[:2, :2]).max())
    assert 0.2 < sigma < 0.22
    with pytest.raises(ValueError, match="positive"):
        EKFConfig(fix_sigma=0.0)


def test_ekf_odometry_moves_the_estimate_and_grows_the_covariance_like_nominal_steps():
    """Measured odometry (a query run's continuous motion): the estimate moves by it in the robot
    frame, and 0.5 m ahead adds the variance of two nominal forward steps."""
    s = started()
    s.predict_odometry((0.5, 0.0, np.radians(30)))
    np.testing.assert_allclose(s.estimate, (0.5, 0.0, np.radians(30)), atol=1e-12)
    cfg = s.config
    assert s.covariance[0, 0] == pytest.approx(cfg.fix_sigma**2 + 2 * cfg.forward_sigma**2)
    assert s.covariance[2, 2] == pytest.approx(
        np.radians(cfg.fix_sigma_deg) ** 2 + 2 * np.radians(cfg.turn_sigma_deg) ** 2
    )
    s.predict_odometry((0.25, 0.1, 0.0))  # along the new heading, 0.1 m to its left
    c, si = np.cos(np.radians(30)), np.sin(np.radians(30))
    np.testing.assert_allclose(s.estimate[:2], (0.5 + 0.25 * c - 0.1 * si, 0.25 * si + 0.1 * c), atol=1e-12)


def test_ekf_recaptures_a_drifted_estimate_after_kidnap_fixes_despite_its_support():
    """A forward step blocked without the pixels showing it: the estimate runs 0.25 m ahead of the
    robot and the right fixes fall outside the gate; within ``drift_m`` (0.5 m) three consistent
    ones re-capture it, however many fixes it accepted before (the A* test episode of
    tests/test_pixels_only.py)."""
    s = started()
    drive(s, [Action.TURN_LEFT] * 8, [np.array([0.0, 0.0, np.radians(15) * (n + 1)]) for n in range(8)])
    yaw = np.radians(120)
    s.predict(Action.FORWARD, IMAGES[1])  # blocked, yet the image changed: the estimate moves
    s.correct(None)
    outcomes, _ = turn_left_with_fixes(s, yaw, (0.0, 0.0), [IMAGES[2 + n % 2] for n in range(4)])
    assert outcomes == ["rejected", "rejected", "reset", "accepted"]
    np.testing.assert_allclose(s.estimate[:2], (0.0, 0.0), atol=0.01)


def test_ekf_prior_is_its_fix_gate_while_its_position_is_narrower_than_a_gross_error():
    s = ekf()
    assert s.prior() is None  # no estimate yet
    s = started()
    cfg = s.config
    # Right after the first estimate (P = a fix's covariance): the gate of a fix, 3.77 sigma of the
    # sum of both, 0.27 m and 10.7 deg (within 0.4 m / 25 deg).
    prior = s.prior()
    np.testing.assert_allclose(prior.pose, s.estimate)
    assert prior.max_distance == pytest.approx(np.sqrt(cfg.gate_chi2 * 2) * cfg.fix_sigma)
    assert np.degrees(prior.max_yaw) == pytest.approx(np.sqrt(cfg.gate_chi2 * 2) * cfg.fix_sigma_deg)
    # A fix inside the prior is one the EKF accepts.
    s.predict(Action.FORWARD, IMAGES[1])
    inside = s.prior().pose + [0.9 * s.prior().max_distance, 0.0, 0.0]
    assert s.prior().admits(_camera(inside)) and s.mahalanobis2(inside) <= cfg.gate_chi2
    # Turning while lost widens the yaw bound (1.5 deg of sigma per 15 deg turn), past 25 deg after
    # 17 turns: no prior (an estimate 4-5 deg off in yaw after a few turns still bounds the pose).
    turns = 0
    while s.prior() is not None:
        s.predict(Action.TURN_LEFT, IMAGES[1 + turns % 3])
        s.correct(None)
        turns += 1
    assert turns == 17
    assert np.degrees(np.sqrt(cfg.gate_chi2 * (s.covariance[2, 2] + cfg.fix_covariance[2, 2]))) > 25.0
    with pytest.raises(ValueError, match="positive"):
        EKFConfig(prior_max_m=0.0)


def _camera(pose) -> np.ndarray:
    """A camera pose at the planar ``pose`` (x, y, yaw), 20 deg down."""
    from vgpnav_env.geometry import camera_pose

    return camera_pose([pose[0], pose[1], 1.2], pose[2], np.radians(20.0))
