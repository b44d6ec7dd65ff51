"""Proprioception (previous action + bump sensor) in the observation, the recipe's collision
penalty, and a resumed run keeping its logged progress and curriculum stage."""

from __future__ import annotations

import pytest

from vgpnav_env.make import make_env

CONFIG = {"scene": "home", "perception": "model", "env": {"image_size": [40, 30], "max_steps": 50}}


def test_observation_has_the_previous_action_and_the_bump_sensor():
    env = make_env({**CONFIG, "proprioception": True})
    assert env.observation_space["last_action"].n == 4 and env.observation_space["bumped"].n == 2
    obs, _ = env.reset(seed=0)
    assert obs["last_action"] == 0 and obs["bumped"] == 0  # STOP stands for "no action yet"
    # Seed 0 starts facing a wall: every forward step is blocked, and the sensor says so.
    blocked = []
    for _ in range(5):
        obs, _, _, _, info = env.step(1)
        assert obs["last_action"] == 1 and obs["bumped"] == int(info["blocked"])
        blocked.append(info["blocked"])
    assert all(blocked)
    obs, _, _, _, info = env.step(2)
    assert obs["last_action"] == 2 and obs["bumped"] == 0 and not info["blocked"]
    obs, _ = env.reset(seed=0)
    assert obs["last_action"] == 0 and obs["bumped"] == 0
    env.close()
    with pytest.raises(ValueError, match="'proprioception'.* needs config\\['perception'\\]"):
        make_env({"scene": "home", "proprioception": True})


def test_end_penalty_charges_blocked_steps():
    from vgpnav_env.agents.ppo import COLLISION_PENALTY, EndPenalty

    plain, wrapped = make_env(CONFIG), EndPenalty(make_env(CONFIG))
    for env in (plain, wrapped):
        env.reset(seed=0)
    (_, r_plain, _, _, info), (_, r_wrapped, *_) = plain.step(1), wrapped.step(1)
    assert info["blocked"] and r_wrapped == pytest.approx(r_plain - COLLISION_PENALTY)
    (_, r_plain, _, _, info), (_, r_wrapped, *_) = plain.step(2), wrapped.step(2)
    assert not info["blocked"] and r_wrapped == pytest.approx(r_plain)


def test_resume_keeps_progress_rows_and_the_curriculum_stage(tmp_path):
    from vgpnav_env.agents.ppo import curriculum_stage, keep_progress, progress_rows

    tb = tmp_path / "tb"
    tb.mkdir()
    rows = [(512, 2.0), (1024, 3.0), (1536, 4.0)]
    text = "time/total_timesteps,curriculum/max_geodesic\n" + "".join(f"{s},{g}\n" for s, g in rows)
    (tb / "progress.csv").write_text(text)
    assert curriculum_stage(tmp_path) == 4.0
    keep_progress(tmp_path, 1024)  # resumed from the 1024-step checkpoint: later rows are redone
    assert not (tb / "progress.csv").exists()
    assert [r["time/total_timesteps"] for r in progress_rows(tmp_path)] == ["512", "1024"]
    assert curriculum_stage(tmp_path) == 3.0
    (tb / "progress.csv").write_text("time/total_timesteps,rollout/spl\n1536,0.5\n")
    assert [r["time/total_timesteps"] for r in progress_rows(tmp_path)] == ["512", "1024", "1536"]
    assert curriculum_stage(tmp_path) == 3.0


def test_loop_detector_finds_repeated_input_at_a_repeated_dead_reckoned_pose():
    """A repeat needs the same input and the same dead-reckoned pose within the window: a left and
    a right turn come back (a loop), a full turn in place only after 24 steps, a blocked forward
    step stays (pushing into a wall), an unblocked one moves on, another input is no repeat."""
    import numpy as np

    from vgpnav_env.agents.proprioception import LoopDetector
    from vgpnav_env.robot import Action

    a, b = {"map": np.zeros((1, 4, 4), np.uint8), "goal_rel": np.array([1.0, 0.5])}, {"last_action": 2}

    def walk(detector, actions, blocked=False, obs=a):
        found = []
        for action in actions:
            found.append(detector.visit(obs, blocked))
            detector.record(action)
        return found

    loops = LoopDetector()
    assert walk(loops, [Action.TURN_LEFT, Action.TURN_RIGHT, Action.TURN_LEFT]) == [False, False, True]
    loops.reset()
    assert walk(loops, [Action.TURN_RIGHT] * 26) == [False] * 24 + [True, True]
    loops.reset()
    assert walk(loops, [Action.FORWARD] * 3, blocked=True) == [False, True, True]
    loops.reset()
    assert walk(loops, [Action.FORWARD] * 30) == [False] * 30
    loops.reset()
    assert walk(loops, [Action.TURN_LEFT, Action.TURN_RIGHT]) == [False, False]
    assert loops.visit(b, False) is False
    assert LoopDetector(window=2).visit(a, False) is False
