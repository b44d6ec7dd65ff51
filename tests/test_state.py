"""The pose state between frames: dead reckoning, stall detection from pixels, the odometry gate."""

from __future__ import annotations

import numpy as np
import pytest

from vgpnav_env.perception.state import GateConfig, OdometryState
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
