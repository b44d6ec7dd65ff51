"""Each recovery strategy of :data:`~vgpnav_env.perception.recovery.RECOVERY` on its own, called
directly on one frame of the tiny build (the perceiver's stages run once, the strategy alone)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from test_pipeline import FAST_VLAD, _known_failures, _no_consensus, _one_pair, errors
from tiny_build import QUERY_HEIGHT

import vgpnav_env.perception.recovery as recovery
from vgpnav_env.perception.backbones.base import Privileged
from vgpnav_env.perception.database import Database, DatabaseConfig
from vgpnav_env.perception.pipeline import Clock, Perceiver, PerceptionConfig
from vgpnav_env.perception.recovery import RECOVERY, Frame, Outcome, Phase
from vgpnav_env.perception.retrieval import select_references
from vgpnav_env.perception.verify import LostReason, PoseGate
from vgpnav_env.robot import base_pose
from vgpnav_env.runs import load_run, load_run_depth

I = 2  # the query frame all tests perceive


@pytest.fixture(scope="module")
def database(tiny_build_dir: Path) -> Database:
    return Database.open(tiny_build_dir, config=DatabaseConfig(vlad=FAST_VLAD, prior_stride=3))


@pytest.fixture(scope="module")
def query(tiny_build_dir: Path):
    return load_run(tiny_build_dir / "query"), load_run_depth(tiny_build_dir / "query")


def _frame(query, prior: PoseGate | None = None, predicted=None) -> Frame:
    run, depth = query
    priv = Privileged(run.poses[I], np.zeros((0, 4, 4)), depth[I])
    return Frame(run.images[I], priv, None, predicted, prior, Clock())


def _prior(query, offset=(0.05, 0.05, 2.0)) -> PoseGate:
    run, _ = query
    dx, dy, deg = offset
    return PoseGate(base_pose(run.poses[I]) + [dx, dy, np.radians(deg)], 0.25, np.radians(9.0))


def test_the_list_is_ordered_pose_strategies_first() -> None:
    names = [s.name for s in RECOVERY]
    assert names == [
        "second round",
        "prior consensus",
        "single pair",
        "prior retry",
        "prior placement",
        "slide",
    ]
    phases = [s.phase for s in RECOVERY]
    assert phases == sorted(phases, key=[Phase.POSE, Phase.RESULT].index)


def test_second_round_alone_replaces_a_round_of_failed_pairs(database: Database, query) -> None:
    run, _ = query
    config = PerceptionConfig(camera_height=QUERY_HEIGHT)
    first = select_references(database.index.similarity(run.images[I]), database.poses, config.retrieval)
    perceiver = Perceiver(database, _known_failures(first[1:], seed=0), config=config)
    frame = _frame(query)
    loc = perceiver._localize(frame)
    assert not loc.ok and loc.reason == LostReason.NO_CONSENSUS or loc.motion.inliers.sum() < 3
    again = recovery.second_round(perceiver, frame, loc)
    assert again is not None and again.ok and again.motion.inliers.sum() >= 3
    assert (
        again.references[0] == first[0] and again.other is not None
    )  # the first round stays for verification
    assert np.array_equal(again.retrieved, loc.retrieved)
    dt, dr = errors(again.motion.T_wq, run.poses[I])
    assert dt < 0.05 and dr < 0.5
    # A round with enough consistent references needs none.
    good = Perceiver(database, "simulated", config=config)
    assert recovery.second_round(good, frame, good._localize(frame)) is None


def test_single_pair_alone_places_a_failed_consensus_by_its_best_pair(database: Database, query) -> None:
    config = PerceptionConfig(camera_height=QUERY_HEIGHT)
    perceiver = Perceiver(database, _one_pair(seed=0), config=config)
    frame = _frame(query)
    loc = perceiver._localize(frame)
    assert not loc.ok
    placed = recovery.single_pair(perceiver, frame, loc)
    assert placed is not None and placed.ok and placed.motion.reason == "single reference"
    assert placed.detail.startswith("single-pair fallback")
    assert recovery.single_pair(perceiver, frame, placed) is None  # only for a failed consensus


def test_prior_consensus_alone_needs_a_prior_the_pairs_agree_with(database: Database, query) -> None:
    run, _ = query
    perceiver, _ = _no_consensus(database, query)
    # Motion averaging over all pairs fails; over the pairs agreeing with the prior it must too
    # (min_consensus 100): None. With a consensus of 2, the agreeing pairs place the frame.
    frame = _frame(query, prior=_prior(query))
    loc = perceiver._localize(frame)
    assert not loc.ok and loc.reason == LostReason.NO_CONSENSUS
    assert recovery.prior_consensus(perceiver, frame, loc) is None
    easy = replace(perceiver.config, averaging=replace(perceiver.config.averaging, min_consensus=2))
    p = Perceiver(database, perceiver.backbone, config=easy)
    p.reset(perceiver.anchor)
    placed = recovery.prior_consensus(p, frame, loc)
    assert placed is not None and placed.ok and placed.detail.startswith("pairs agreeing with the prior")
    assert errors(placed.motion.T_wq, run.poses[I])[0] < 0.3
    assert recovery.prior_consensus(p, _frame(query), loc) is None  # no prior: nothing to agree with


def test_prior_retry_alone_tries_references_around_the_prior(database: Database, query) -> None:
    run, depth = query
    config = PerceptionConfig(camera_height=QUERY_HEIGHT)
    sims = database.index.similarity(run.images[I])
    first = select_references(sims, database.poses, config.retrieval)
    untried = [j for j in np.argsort(-sims, kind="stable") if j not in first][: config.retrieval.k]
    perceiver = Perceiver(database, _known_failures([*first.tolist(), *untried], seed=0), config=config)
    perceiver.initialize(run.images[0], Privileged(run.poses[0], np.zeros((0, 4, 4)), depth[0]))
    frame = _frame(query, prior=_prior(query))
    lost = perceiver.attempt(frame, None)
    assert not lost.result.localized and lost.result.source == "global"
    outcome = recovery.prior_retry(perceiver, frame, Outcome(lost, (lost,)))
    assert outcome is not None and outcome.attempt.result.localized
    assert outcome.attempt.result.source == "tracking" and outcome.lost[-1] is lost
    assert errors(outcome.attempt.result.T_wc, run.poses[I])[0] < 0.02
    # Without a prior, or once localized, nothing to retry.
    assert recovery.prior_retry(perceiver, _frame(query), Outcome(lost, (lost,))) is None
    assert recovery.prior_retry(perceiver, frame, outcome) is None


def test_prior_placement_alone_places_a_lost_frame_inside_the_prior(database: Database, query) -> None:
    run, _ = query
    perceiver, _ = _no_consensus(database, query)
    frame = _frame(query, prior=_prior(query))
    lost = perceiver.attempt(frame, None)
    assert not lost.result.localized
    outcome = recovery.prior_placement(perceiver, frame, Outcome(lost, (lost,)))
    assert outcome is not None and outcome.attempt.result.prior_placed and outcome.lost == ()
    dt, dr = errors(outcome.attempt.result.T_wc, run.poses[I])
    assert dt < 0.05 and dr < 1.0
    away = _frame(query, prior=_prior(query, (1.0, 0.0, 0.0)))
    assert recovery.prior_placement(perceiver, away, Outcome(lost, (lost,))) is None


def test_slide_alone_moves_a_verified_pose_only_inside_a_prior(
    database: Database, query, monkeypatch: pytest.MonkeyPatch
) -> None:
    run, depth = query
    config = PerceptionConfig(camera_height=QUERY_HEIGHT)
    perceiver = Perceiver(database, "simulated", config=config)
    perceiver.initialize(run.images[0], Privileged(run.poses[0], np.zeros((0, 4, 4)), depth[0]))

    def slide(T_wq: np.ndarray, *args) -> tuple[np.ndarray, float]:
        moved = T_wq.copy()
        moved[0, 3] += 0.005
        return moved, 1.0

    monkeypatch.setattr(recovery, "slide_on_ray", slide)
    frame = _frame(query, prior=_prior(query, (0.0, 0.0, 0.0)))
    verified = perceiver.attempt(frame, None)
    assert verified.result.localized
    slid = recovery.slide(perceiver, frame, Outcome(verified))
    assert slid is not None and slid.attempt.result.verdict.ok
    shift = slid.attempt.result.T_wc[:3, 3] - verified.result.T_wc[:3, 3]
    np.testing.assert_allclose(shift, [0.005, 0.0, 0.0], atol=1e-9)
    assert recovery.slide(perceiver, _frame(query), Outcome(verified)) is None  # no prior: it stands
