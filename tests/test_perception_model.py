"""The privileged ``model`` perception: fitting, the shipped fit, determinism and its draws in the env."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from vgpnav_env import make_env
from vgpnav_env.perception.model import (
    ModelObservation,
    PerceptionModel,
    PriorErrors,
    fit_model,
    fit_prior_errors,
    median_depth,
)
from vgpnav_env.perception.occupancy import OCCUPIED

ENV_ID = "VGPNav/PointGoal-v0"
SIZE = (40, 30)

#: The known model synthetic calibration data are drawn from.
TRUE = PerceptionModel(
    depth_edges=[1.0, 2.0],
    p_lost=[0.5, 0.2, 0.05],
    stickiness=0.4,
    p_gross=0.08,
    log_translation=(np.log(0.01), 0.8),
    log_rotation=(np.log(0.1), 0.6),
    gross_translation_m=[3.0, 6.0],
    gross_rotation_deg=[2.0, 180.0],
    depth_noise_m=0.05,
    coverage=0.8,
)


def synthetic_records(model: PerceptionModel, n: int, seed: int) -> tuple[list[dict], np.ndarray]:
    """``n`` consecutive query frames drawn from ``model`` (records as the localization report's)."""
    rng = np.random.default_rng(seed)
    depths = rng.uniform(0.5, 3.0, n)
    records, lost = [], False
    for i, d in enumerate(depths):
        lost = bool(rng.random() < model.lost_probability(d, lost))
        t, r = (np.nan, np.nan) if lost else model.pose_error(rng)
        records.append(
            {
                "frame": i,
                "status": "lost" if lost else "localized",
                "translation_m": t,
                "rotation_deg": r,
                # A frame's Acc: the mean distance of its points (here 50, off by the depth noise).
                "acc_m": np.nan if lost else np.abs(rng.normal(0.0, model.depth_noise_m, 50)).mean(),
                "n_points": 0 if lost else int(rng.binomial(1000, model.coverage)),
            }
        )
    return records, depths


def test_fit_recovers_the_model_it_was_drawn_from():
    records, depths = synthetic_records(TRUE, 6000, seed=1)
    fit = fit_model(records, depths, sampled_pixels=1000, n_bins=3)
    # Bins are the depth terciles (~ 1.33 and 2.17 m for uniform(0.5, 3)); the lost rate per bin
    # matches the data's within 0.01, and the stickiness the true one within 0.08.
    bins = np.searchsorted(fit.depth_edges, depths, side="right")
    lost = np.array([r["status"] == "lost" for r in records])
    for b in range(3):
        assert fit.p_lost[b] == pytest.approx(lost[bins == b].mean(), abs=0.01)
    assert fit.stickiness == pytest.approx(TRUE.stickiness, abs=0.08)
    assert fit.p_gross == pytest.approx(TRUE.p_gross, abs=0.015)
    assert fit.log_translation[0] == pytest.approx(TRUE.log_translation[0], abs=0.05)
    assert fit.log_rotation[1] == pytest.approx(TRUE.log_rotation[1], abs=0.05)
    assert set(fit.gross_translation_m) == {3.0, 6.0}
    assert fit.depth_noise_m == pytest.approx(TRUE.depth_noise_m, rel=0.1)
    assert fit.coverage == pytest.approx(TRUE.coverage, abs=0.01)


def test_shipped_fit_matches_the_measured_classical_run():
    """The default fit came from ``vgpnav eval localization home --queries 0`` (classical, 320x240):
    184 frames, 36 lost (20%), 9 gross among 148 localized, median error 0.004 m / 0.09 deg."""
    fit = PerceptionModel.load()
    # Quartile bins hold equal counts; Laplace smoothing ((k + 1) / (n + 2), n = 46) adds ~0.012.
    assert np.mean(fit.p_lost) == pytest.approx(36 / 184, abs=0.015)
    assert fit.p_lost[0] > 2 * fit.p_lost[2]  # close views (median depth < 1.34 m) are lost more
    assert fit.p_gross == pytest.approx(9 / 148, abs=1e-9) and len(fit.gross_translation_m) == 9
    assert np.exp(fit.log_translation[0]) == pytest.approx(0.004, rel=0.5)
    assert fit.source["scene"] == "home" and fit.source["backbone"] == "classical"


@pytest.fixture(scope="module")
def model_env(walled_room):
    env = ModelObservation(
        gym.make(ENV_ID, scene=walled_room, image_size=SIZE, render_rgb=False, max_steps=60)
    )
    yield env
    env.close()


def _rollout(env, seed: int, steps: int):
    rng = np.random.default_rng(seed)
    obs, info = env.reset(seed=seed)
    out = [(obs, info)]
    for _ in range(steps):
        obs, _, terminated, truncated, info = env.step(int(rng.choice([1, 1, 2, 3])))
        out.append((obs, info))
        if terminated or truncated:
            obs, info = env.reset()
            out.append((obs, info))
    return out


def test_same_seed_same_draws_and_space(model_env):
    a, b = _rollout(model_env, 5, 40), _rollout(model_env, 5, 40)
    for (oa, _), (ob, _) in zip(a, b, strict=True):
        assert model_env.observation_space.contains(oa)
        for key in oa:
            np.testing.assert_array_equal(oa[key], ob[key])
    c = _rollout(model_env, 6, 40)
    assert any(not np.array_equal(x[0]["pose"], y[0]["pose"]) for x, y in zip(a, c, strict=False))


def test_map_measures_off_changes_nothing_but_the_map_entries(model_env, walled_room):
    """Training's ``map_measures=False``: the same draws and observations, no map scores in info."""
    off = ModelObservation(
        gym.make(ENV_ID, scene=walled_room, image_size=SIZE, render_rgb=False, max_steps=60),
        map_measures=False,
    )
    keys = {"map_precision", "map_recall", "map_iou", "path_phantoms"}
    try:
        a, b = _rollout(model_env, 5, 30), _rollout(off, 5, 30)
    finally:
        off.close()
    assert all(keys <= set(info) for _, info in a)
    for (oa, ia), (ob, ib) in zip(a, b, strict=True):
        assert not keys & set(ib)
        for key in oa:
            np.testing.assert_array_equal(oa[key], ob[key])
        assert ia["collisions"] == ib["collisions"]


def test_draws_in_the_env_follow_the_fit(walled_room):
    """Over 1500 steps: the lost rate per depth bin, the gross rate and the inlier error median are
    those of the fit (binomial tolerances ~3 sigma); lost frames carry the pose by odometry."""
    env = ModelObservation(
        gym.make(ENV_ID, scene=walled_room, image_size=SIZE, render_rgb=False, max_steps=60), fit=TRUE
    )
    frames = _rollout(env, 0, 1500)
    lost = np.array([not o["localized"] for o, _ in frames])
    err = np.array([i["localization_error_m"] for _, i in frames])
    depth_bins = []
    for _, info in frames:
        d = env.unwrapped.render_depth(info["pose"])[::4, ::4]
        depth_bins.append(np.searchsorted(TRUE.depth_edges, median_depth(d), side="right"))
    depth_bins = np.asarray(depth_bins)
    # Stickiness keeps the marginal lost rate of a bin at p_lost (stationary chain).
    for b, p in enumerate(TRUE.p_lost):
        n = (depth_bins == b).sum()
        if n > 100:
            assert lost[depth_bins == b].mean() == pytest.approx(p, abs=3 * np.sqrt(p * (1 - p) / n) + 0.03)
    fixes = err[~lost]
    assert np.mean(fixes > 1.0) == pytest.approx(TRUE.p_gross, abs=0.03)
    assert np.median(fixes[fixes < 0.5]) == pytest.approx(0.01, rel=0.25)
    env.close()


def test_map_starts_from_the_base_layout_and_fuses_depth():
    env = make_env(
        {"scene": "home", "perception": "model", "env": {"image_size": [40, 30], "render_rgb": False}}
    )
    obs, info = env.reset(seed=0)
    assert (obs["map"] == OCCUPIED).mean() > 0.02  # walls of the prior around the robot
    fused = env.get_wrapper_attr("fused_map")
    before = fused.logodds.copy()
    for _ in range(5):
        obs, *_ = env.step(2)
    assert not np.array_equal(before, fused.logodds)  # localized frames fused depth
    env.close()


def test_a_blocked_forward_step_marks_the_felt_obstacle_in_the_map():
    """Home seed 0 starts facing a wall. Without the prior (and with the depth of the wall hidden,
    as a randomised episode's unseen cells hide it) the map holds nothing ahead until the robot
    bumps: the bump marks the cells ahead occupied; a turn marks nothing."""
    env = ModelObservation(
        gym.make(ENV_ID, scene="home", image_size=SIZE, render_rgb=False, max_steps=60), prior=False
    )
    obs, _ = env.reset(seed=0)
    env.unseen = np.ones(env.fused_map.spec.shape, bool)
    centre = obs["map"].shape[-1] // 2
    obs, _, _, _, info = env.step(2)  # a turn: nothing felt
    assert not info["blocked"] and (env.fused_map.logodds < env.fused_map.clamp[1]).all()
    obs, _, _, _, info = env.step(3)
    obs, _, _, _, info = env.step(1)
    assert info["blocked"]
    front = obs["map"][0, centre - 4 : centre - 1, centre - 1 : centre + 1]  # 0.15-0.35 m ahead
    assert (front == OCCUPIED).any(), obs["map"][0, centre - 5 : centre + 1, centre - 3 : centre + 3]
    marked = np.argwhere(env.fused_map.logodds == env.fused_map.clamp[1])
    ahead = (env.fused_map.spec.cell_to_world(marked) - env.estimate[:2]) @ [
        np.cos(env.estimate[2]),
        np.sin(env.estimate[2]),
    ]
    assert len(marked) >= 3 and np.all(np.abs(ahead - 0.25) < 0.1)
    env.close()


def test_calibrate_reads_the_builds_query_depth(home_build):
    """``calibrate`` bins the records by the median ground-truth depth of their query views."""
    from vgpnav_env.eval.calibrate import calibrate
    from vgpnav_env.runs import load_run_depth

    depth = load_run_depth(home_build / "query")
    n = min(len(depth), 40)
    medians = np.array([median_depth(d) for d in depth[:n]])
    # Lost exactly when the view is closer than its median: the fit must put all losses in the
    # near bins (Laplace-smoothed: (k + 1) / (n + 2)).
    records = [
        {"frame": i, "status": "lost" if m < np.median(medians) else "localized", "translation_m": 0.01,
         "rotation_deg": 0.1, "acc_m": 0.02, "n_points": 1000}
        for i, m in enumerate(medians)
    ]  # fmt: skip
    fit = calibrate(home_build, records, {"scene": "home"})
    width, height = depth.shape[2], depth.shape[1]
    assert fit.source["image size"] == f"{width}x{height}" and fit.source["scene"] == "home"
    assert fit.p_lost[0] > 0.8 and fit.p_lost[-1] < 0.2
    # The pipeline samples every 2nd pixel in both directions.
    assert fit.coverage == pytest.approx(1000 / (-(-width // 2) * -(-height // 2)), rel=1e-6)


def test_pose_state_covariance_grows_while_lost(model_env):
    """The model wrapper's ``pose_state`` (as the pixel wrapper's): the fit's fix covariance on a
    fix, plus the EKF's forward-step noise per forward step while lost."""
    from vgpnav_env.perception.state import EKFConfig

    state = model_env.pose_state
    fix = model_env.model.fix_covariance()
    obs, _ = model_env.reset(seed=1)
    np.testing.assert_allclose(state.covariance, fix)
    np.testing.assert_allclose(state.estimate, obs["pose"], atol=1e-5)  # the observation is float32
    state.update(state.estimate, localized=False, action=1)
    state.update(state.estimate, localized=False, action=1)
    sigma2 = np.linalg.eigvalsh(state.covariance[:2, :2]).max()
    assert sigma2 == pytest.approx(fix[0, 0] + 2 * EKFConfig().forward_sigma ** 2, rel=1e-6)
    state.update(state.estimate, localized=True, action=2)
    np.testing.assert_allclose(state.covariance, fix)


#: Known database-prior errors the synthetic prior is drawn from.
PRIOR_ERRORS = PriorErrors(
    free_edges=[0.1, 0.3],
    free_occupied=[0.4, 0.1, 0.01],
    free_unknown=[0.2, 0.1, 0.05],
    obstacle_edges=[0.1, 0.3],
    obstacle_occupied=[0.7, 0.6, 0.8],
    obstacle_unknown=[0.2, 0.3, 0.1],
)


def test_prior_errors_fit_recovers_the_rates_they_were_drawn_with():
    """A prior drawn from known errors on a grid of walls and boxes (0.05 m cells) fits back to them:
    every bin's occupied and unknown rates within 0.03 (bins hold >= 900 cells; the blobs make
    the draws correlated, hence the tolerance)."""
    obstacle = np.zeros((300, 300), bool)
    obstacle[:4], obstacle[-4:], obstacle[:, :4], obstacle[:, -4:] = True, True, True, True
    for r in range(20, 260, 70):
        for c in range(20, 260, 70):
            obstacle[r : r + 40, c : c + 30] = True
    free = ~obstacle
    logodds = PRIOR_ERRORS.draw(free, obstacle, 0.05, np.random.default_rng(0))
    fit = fit_prior_errors(1 / (1 + np.exp(-logodds)), free, obstacle, 0.05, (0.1, 0.3), (0.1, 0.3))
    for got, want in [
        (fit.free_occupied, PRIOR_ERRORS.free_occupied),
        (fit.free_unknown, PRIOR_ERRORS.free_unknown),
        (fit.obstacle_occupied, PRIOR_ERRORS.obstacle_occupied),
        (fit.obstacle_unknown, PRIOR_ERRORS.obstacle_unknown),
    ]:
        np.testing.assert_allclose(got, want, atol=0.03)
    with pytest.raises(ValueError, match="one shape"):
        fit_prior_errors(np.zeros((3, 3)), free, obstacle, 0.05)


def test_shipped_fit_has_the_database_priors_errors():
    """Measured on home's 320x240 build against the base layout: free cells within 0.1 m of an
    obstacle are occupied in the database prior 44 % of the time, beyond 0.5 m 0.2 %; obstacle
    cells 56-80 % occupied (the rest unknown or free: hollow furniture)."""
    errors = PerceptionModel.load().prior_errors
    assert errors.free_occupied[0] == pytest.approx(0.44, abs=0.01)
    assert errors.free_occupied[-1] < 0.005
    assert 0.5 < min(errors.obstacle_occupied) and max(errors.obstacle_occupied) < 0.85


def _episode_stats(env, seeds, steps=30):
    lost, no_estimate, first = [], [], []
    for seed in seeds:
        obs, info = env.reset(seed=seed)
        first.append((obs, env.get_wrapper_attr("fused_map").logodds.copy()))
        no_estimate.append(not env.get_wrapper_attr("has_estimate"))
        frames = []
        for k in range(steps):
            obs, _, terminated, truncated, info = env.step([1, 1, 2, 1, 3][k % 5])
            frames.append(1 - obs["localized"])
            if terminated or truncated:
                break
        lost.append(np.mean(frames))
    return np.array(lost), np.array(no_estimate), first


def test_randomised_episodes_lose_more_start_without_estimate_and_degrade_the_prior():
    """``randomize=True`` on home (shipped fit): over 12 episodes the mean lost fraction exceeds the
    plain model's by > 0.1, some episodes start without an estimate (the placeholder at the map
    centre), the prior differs from the ground-truth one on 2-40 % of the known cells and differs
    between episodes, and a seed repeats its draws."""
    config = {"scene": "home", "perception": "model", "env": {"image_size": [40, 30], "render_rgb": False}}
    plain = make_env(config)
    randomised = make_env({**config, "wrapper": {"randomize": True}})
    seeds = range(12)
    lost_plain, none_plain, first_plain = _episode_stats(plain, seeds)
    lost_rand, none_rand, first_rand = _episode_stats(randomised, seeds)
    assert lost_rand.mean() > lost_plain.mean() + 0.1
    assert not none_plain.any() and none_rand.any()
    centre = np.array(randomised.get_wrapper_attr("fused_map").spec.centre)
    obs = first_rand[int(np.argmax(none_rand))][0]
    np.testing.assert_allclose(obs["pose"], [*centre, 0.0], atol=1e-5)
    truth = first_plain[0][1]
    known = truth != 0
    changed = np.mean(np.sign(first_rand[0][1][known]) != np.sign(truth[known]))
    assert 0.02 < changed < 0.4
    assert not np.array_equal(first_rand[0][1], first_rand[1][1])
    again, _, first_again = _episode_stats(randomised, [0])
    assert again[0] == lost_rand[0] and np.array_equal(first_again[0][1], first_rand[0][1])
    plain.close()
    randomised.close()


def test_randomised_episodes_hide_the_obstacles_of_unseen_cells_from_depth():
    """Randomised episodes draw unseen cells (a fraction in [0, MAX_UNSEEN] of the map, mean over
    12 episodes within 0.1 of MAX_UNSEEN / 2, differing between episodes): depth adds no obstacle
    evidence there. Never lost, with every cell unseen no cell's log-odds rises over 10 steps
    turning in place; with none, some do. The plain model has no unseen cells."""
    import dataclasses

    from vgpnav_env.perception.model import MAX_UNSEEN, ModelObservation

    config = {"scene": "home", "perception": "model", "env": {"image_size": [40, 30], "render_rgb": False}}
    plain, env = make_env(config), make_env({**config, "wrapper": {"randomize": True}})
    plain.reset(seed=0)
    assert plain.get_wrapper_attr("unseen") is None
    fractions = []
    for seed in range(12):
        env.reset(seed=seed)
        fractions.append(float(env.get_wrapper_attr("unseen").mean()))
    assert 0.0 <= min(fractions) and max(fractions) <= MAX_UNSEEN + 0.01
    assert abs(np.mean(fractions) - MAX_UNSEEN / 2) < 0.1 and len(set(fractions)) > 1
    model = env
    while not isinstance(model, ModelObservation):
        model = model.env
    model.model = dataclasses.replace(model.model, p_lost=[0.0] * len(model.model.p_lost))
    rises = []
    for everywhere in (True, False):
        model.reset(seed=0)
        model.unseen = np.full(model.fused_map.spec.shape, everywhere)
        model._lost, model._stickiness = False, 0.0
        before = model.fused_map.logodds.copy()
        for _ in range(10):
            model.step(3)  # turn right: views all around
        rises.append(int((model.fused_map.logodds > before + 1e-6).sum()))
    assert rises[0] == 0 and rises[1] > 0
    plain.close()
    env.close()
