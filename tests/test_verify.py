"""The pose checks of perception.verify on hand-made motion results and synthetic matches (no rendering)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vgpnav_env.geometry import PinholeCamera, camera_pose, invert_pose, make_pose
from vgpnav_env.perception.backbones.base import BackboneOutput
from vgpnav_env.perception.backbones.classical import in_front_of_both, triangulate_query_depth
from vgpnav_env.perception.motion_averaging import MotionAveragingConfig, MotionResult, average_motion
from vgpnav_env.perception.recovery import (
    RecoveryConfig,
    pooled_pairs,
    prior_poses,
    prior_support_floor,
    slide_on_ray,
)
from vgpnav_env.perception.scale_recovery import GroundAnchor, GroundEstimate, ScaleEstimate
from vgpnav_env.perception.verify import (
    Pairs,
    PoseGate,
    VerifyConfig,
    check_height,
    check_scale,
    epipolar_support,
    explained_confidence,
    off_plane_matches,
    pair_support,
    plausible_scale,
    prior_hypothesis,
    prior_pairs,
    refine_pose,
    rival_pairs,
    verify_pose,
)
from vgpnav_env.robot import base_pose


def _motion(z: float, reason: str = "") -> MotionResult:
    T = camera_pose([1.0, 2.0, z], 0.0, np.deg2rad(20.0))
    return MotionResult(T, np.ones(3), np.ones(3, bool), 3, True, reason)


def test_check_height_rejects_a_pose_off_the_calibrated_camera_height() -> None:
    anchor, config = GroundAnchor(), VerifyConfig(pose_height_tolerance=0.3)
    assert check_height(_motion(2.0), anchor, 1.2, config).ok  # no anchor yet: no check
    anchor.initialize([(_motion(1.2).T_wq, None)], 1.2)  # floor at z = 0
    assert check_height(_motion(1.45), anchor, 1.2, config).ok
    high = _motion(1.6)
    failed = check_height(high, anchor, 1.2, config)
    assert not failed.ok and failed.reason == "camera height off by +0.40 m"
    assert high.ok and high.reason == ""  # a new result: the input is not changed
    assert check_height(_motion(1.6, "single reference"), anchor, 1.2, config).ok  # no metric height
    assert check_height(high, anchor, 1.2, VerifyConfig(pose_height_tolerance=None)).ok
    with pytest.raises(ValueError, match="pose_height_tolerance"):
        VerifyConfig(pose_height_tolerance=0.0)


def test_check_scale_replaces_a_ground_scale_far_from_the_rays() -> None:
    config = VerifyConfig(scale_check_ratio=1.5)
    ground = ScaleEstimate(2.0, "ground")
    assert check_scale(ground, 1.5, config) is ground  # within 1.5x
    assert check_scale(ground, 1.0, config) == ScaleEstimate(1.0, "fallback")  # 2x: a table top
    assert check_scale(ground, float("nan"), config) is ground  # no ray scale to check against
    assert check_scale(ScaleEstimate(1.0, "disabled"), 5.0, config).source == "disabled"
    assert check_scale(ground, 1.0, VerifyConfig(scale_check_ratio=None)) is ground
    with pytest.raises(ValueError, match="scale_check_ratio"):
        VerifyConfig(scale_check_ratio=1.0)


def test_weak_rays_do_not_overrule_a_ground_with_nothing_under_it() -> None:
    # Two nearly parallel rays of weight < 0.1 imply half the scale of a ground peak with < 1 % of
    # the points under it (the floor): the floor stands; a table top has the floor under it.
    config = VerifyConfig(scale_check_ratio=1.5, strong_rays_weight=0.2, max_under_ground=0.03)
    ground = ScaleEstimate(2.0, "ground")
    floor = GroundEstimate(-0.6, 0.1, True, below=0.005)
    table = GroundEstimate(-0.3, 0.1, True, below=0.1)
    assert check_scale(ground, 1.0, config, 0.1, floor) is ground
    assert check_scale(ground, 1.0, config, 0.1, table) == ScaleEstimate(1.0, "fallback")
    assert check_scale(ground, 1.0, config, 0.4, floor) == ScaleEstimate(1.0, "fallback")  # strong
    assert check_scale(ground, 1.0, config) == ScaleEstimate(1.0, "fallback")  # no weight given
    off = replace(config, strong_rays_weight=None)
    assert check_scale(ground, 1.0, off, 0.1, floor) == ScaleEstimate(1.0, "fallback")
    with pytest.raises(ValueError, match="max_under_ground"):
        VerifyConfig(max_under_ground=1.5)


def test_a_scale_that_puts_the_scene_millimetres_away_is_no_scale() -> None:
    # Rays giving 0.005 m per unit put the median confident depth at 5 mm: no scale.
    config = VerifyConfig(min_median_depth_m=0.25)
    rays = ScaleEstimate(0.005, "fallback")
    none = plausible_scale(rays, 1.0, config)
    assert none.source == "none" and np.isnan(none.scale)
    assert not plausible_scale(ScaleEstimate(0.2, "ground"), 1.0, config).ok
    good = ScaleEstimate(0.6, "ground")
    assert plausible_scale(good, 1.0, config) is good  # a wall 0.6 m ahead
    assert plausible_scale(rays, 1.0, VerifyConfig(min_median_depth_m=None)) is rays
    assert plausible_scale(rays, float("nan"), config) is rays  # no confident depth to judge by
    with pytest.raises(ValueError, match="min_median_depth_m"):
        VerifyConfig(min_median_depth_m=0.0)


# Two identical rooms: room B is room A moved 10 m along x (same furniture, same texture). The
# query stands in room A; three references look at the same corner of each room.
CAMERA = PinholeCamera(320, 240, np.deg2rad(60.0))
SHIFT = np.array([10.0, 0.0, 0.0])


def _room_points(rng: np.random.Generator) -> np.ndarray:
    """Textured points on a corner of room A: two walls and the floor (metres, W)."""
    n = 400
    wall_x = np.c_[np.full(n, 4.0), rng.uniform(0, 4, n), rng.uniform(0, 2.5, n)]
    wall_y = np.c_[rng.uniform(0, 4, n), np.full(n, 4.0), rng.uniform(0, 2.5, n)]
    floor = np.c_[rng.uniform(1, 4, n), rng.uniform(1, 4, n), np.zeros(n)]
    return np.concatenate([wall_x, wall_y, floor])


def _matches(T_wq: np.ndarray, T_wi: np.ndarray, points: np.ndarray, rng) -> np.ndarray:
    """(m, 4) pixels of the points both cameras see, with 0.3 px noise."""
    uv_q, ok_q = _project(T_wq, points)
    uv_i, ok_i = _project(T_wi, points)
    ok = ok_q & ok_i
    m = np.hstack([uv_q[ok], uv_i[ok]])
    return (m + rng.normal(0, 0.3, m.shape)).astype(np.float32)


def _project(T_wc: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = (points - T_wc[:3, 3]) @ T_wc[:3, :3]
    uv = p[:, :2] / p[:, 2:3] * CAMERA.K[0, 0] + CAMERA.K[:2, 2]
    inside = (p[:, 2] > 0.1) & (uv >= 0).all(1) & (uv[:, 0] < CAMERA.width) & (uv[:, 1] < CAMERA.height)
    return uv, inside


def _aliased_frame(rooms: str):
    """(true T_wq, the same pose in room B, T_wi, backbone output) with references in ``rooms``."""
    rng = np.random.default_rng(0)
    points = _room_points(rng)
    T_q = camera_pose([1.0, 1.2, 1.2], np.deg2rad(45.0), np.deg2rad(20.0))
    refs_a = [camera_pose([x, y, 1.5], np.deg2rad(yaw), np.deg2rad(25.0)) for x, y, yaw in
              [(0.6, 1.5, 40.0), (1.5, 0.5, 55.0), (1.2, 1.9, 35.0)]]  # fmt: skip
    T_wi, matches = [], []
    for room in rooms:
        offset = SHIFT if room == "B" else 0.0
        for T in refs_a:
            T_i = T.copy()
            T_i[:3, 3] += offset
            T_wi.append(T_i)
            # Identical rooms look identical: the query's view of A matches B's references as A's.
            matches.append(_matches(T_q, T, points, rng))
    k = len(T_wi)
    out = BackboneOutput(
        np.tile(np.eye(4), (k, 1, 1)), np.full(k, 0.5), np.array([len(m) for m in matches]),
        np.zeros((2, 2), np.float32), np.zeros((2, 2), np.float32), "test", "none", matches=matches,
    )  # fmt: skip
    T_b = T_q.copy()
    T_b[:3, 3] += SHIFT
    return T_q, T_b, np.array(T_wi), out


def test_identical_rooms_are_ambiguous_never_the_wrong_room() -> None:
    T_a, T_b, T_wi, out = _aliased_frame("AB")
    config = VerifyConfig()
    for pose, rival in ((T_a, T_b), (T_b, T_a)):
        verdict = verify_pose(pose, Pairs(T_wi, out, CAMERA, config), rivals=[rival])
        assert not verdict.ok and verdict.reason == "ambiguous" and verdict.check == "ambiguity", (
            verdict.detail
        )
        # Each room's references support its pose in full: the rival is as strong as the pose.
        assert verdict.rival_strength >= 0.5 * verdict.strength > 3 * config.min_support_matches
    # Only room A's references: the right room is confirmed by all three, with high confidence.
    T_a, T_b, T_wi, out = _aliased_frame("A")
    right = verify_pose(T_a, Pairs(T_wi, out, CAMERA, config), rivals=[T_b])
    assert right.ok and right.n_supporting == 3 and right.rival_strength == 0 and right.confidence > 0.8


def test_a_rival_room_with_few_views_but_a_pair_as_confident_makes_the_frame_ambiguous() -> None:
    # Hospital:1's paper gross frames (6 m / 2 m off, identical wards): retrieval gives three views
    # of the wrong ward (room B) and one of the right one (room A), which matches only part of the
    # view but is as confident as B's best pair: A's support is under ambiguity_ratio of B's.
    T_a, T_b, T_wi, out = _aliased_frame("AB")
    keep = [3, 4, 5, 0]
    matches = [out.matches[i] for i in keep[:3]] + [out.matches[0][: int(0.4 * len(out.matches[0]))]]
    out = replace(
        out, T_qi=out.T_qi[keep], confidence=np.array([0.5, 0.3, 0.3, 0.5]),
        n_matches=np.array([len(m) for m in matches]), scale_valid=out.scale_valid[keep], matches=matches,
    )  # fmt: skip
    T_wi = T_wi[keep]
    config = VerifyConfig()
    assert config.rival_confidence_ratio == 0.9
    old = replace(config, rival_confidence_ratio=None)
    before = verify_pose(T_b, Pairs(T_wi, out, CAMERA, old), rivals=[T_a])
    # The rule before rival_confidence_ratio: room A is a weaker rival and the wrong room is confirmed.
    assert before.ok and before.rival_strength < config.ambiguity_ratio * 2 * before.support.max()
    wrong = verify_pose(T_b, Pairs(T_wi, out, CAMERA, config), rivals=[T_a])
    assert not wrong.ok and wrong.reason == "ambiguous" and wrong.check == "ambiguity", wrong.detail
    assert "as confident as the pose's best" in wrong.detail and "10.0 m away" in wrong.detail
    # Room A's pair weak (0.2 < 0.9 x 0.5): the support comparison alone decides, as before.
    weak = replace(out, confidence=np.array([0.5, 0.3, 0.3, 0.2]))
    assert verify_pose(T_b, Pairs(T_wi, weak, CAMERA, config), rivals=[T_a]).ok
    # A rival whose matches lie on one plane is no place, however confident its pair.
    flat = replace(config, confident_rival_off_plane=10_000)
    assert verify_pose(T_b, Pairs(T_wi, out, CAMERA, flat), rivals=[T_a]).ok
    with pytest.raises(ValueError, match="rival_confidence_ratio"):
        VerifyConfig(rival_confidence_ratio=0.0)
    with pytest.raises(ValueError, match="confident_rival_off_plane"):
        VerifyConfig(confident_rival_off_plane=-1)


def test_a_confident_prior_picks_the_room_the_robot_is_in_never_the_other() -> None:
    T_a, T_b, T_wi, out = _aliased_frame("AB")
    config = VerifyConfig()
    # The state estimate expects the robot 0.1 m / 3 deg from room A's pose (a 0.25 m / 9 deg prior):
    # room B's equal support no longer makes room A's pose ambiguous; it is confirmed.
    expected = base_pose(T_a) + [0.1, 0.0, np.radians(3.0)]
    prior = PoseGate(expected, 0.25, np.radians(9.0))
    right = verify_pose(T_a, Pairs(T_wi, out, CAMERA, config), rivals=[T_b], prior=prior)
    assert right.ok and right.rival_strength == 0 and right.support[:3].all(), right.detail
    # ...by the prior alone: without it room B makes the same pose ambiguous.
    assert (
        right.by_prior
        and verify_pose(T_a, Pairs(T_wi, out, CAMERA, config), rivals=[T_b]).reason == "ambiguous"
    )
    # Room B's pose lies outside the prior: verified as without one, still ambiguous (never room B).
    wrong = verify_pose(T_b, Pairs(T_wi, out, CAMERA, config), rivals=[T_a], prior=prior)
    assert not wrong.ok and wrong.reason == "ambiguous"
    # A prior around room B confirms nothing in room A, and picks B only where B is expected.
    away = PoseGate(base_pose(T_b), 0.25, np.radians(9.0))
    assert verify_pose(T_a, Pairs(T_wi, out, CAMERA, config), rivals=[T_b], prior=away).reason == "ambiguous"
    # A rival inside the prior still counts: a prior wide enough for both rooms separates nothing.
    both = PoseGate(0.5 * (base_pose(T_a) + base_pose(T_b)), 6.0, np.radians(9.0))
    assert verify_pose(T_a, Pairs(T_wi, out, CAMERA, config), rivals=[T_b], prior=both).reason == "ambiguous"


def test_the_prior_picks_the_rival_in_the_room_the_robot_is_in() -> None:
    T_a, T_b, T_wi, out = _aliased_frame("AB")
    config, averaging = VerifyConfig(), MotionAveragingConfig()
    # The averaged pose landed in room B; room A's view is its rival. The robot is expected in A.
    prior = PoseGate(base_pose(T_a) + [0.05, -0.05, np.radians(2.0)], 0.25, np.radians(9.0))
    assert verify_pose(T_b, Pairs(T_wi, out, CAMERA, config), rivals=[T_a], prior=prior).reason == "ambiguous"
    T, verdict = prior_hypothesis(
        T_b, [T_a], Pairs(T_wi, out, CAMERA, config), prior, scale=1.0, averaging=averaging
    )
    assert T is T_a and verdict.ok and verdict.support[:3].all(), verdict.detail
    # Expected in B (the pose's own room) or elsewhere: no rival inside the prior, nothing picked.
    in_b = PoseGate(base_pose(T_b), 0.25, np.radians(9.0))
    elsewhere = PoseGate(base_pose(T_a) + [3.0, 0.0, 0.0], 0.25, np.radians(9.0))
    for other in (in_b, elsewhere):
        assert (
            prior_hypothesis(
                T_b, [T_a], Pairs(T_wi, out, CAMERA, config), other, scale=1.0, averaging=averaging
            )
            is None
        )
    # A rival inside the prior that the images do not confirm is not picked (room A's references only
    # and a rival turned 8 deg from A's pose: one reference explains 80 of its matches, the others
    # under 10).
    _, _, T_wi_a, out_a = _aliased_frame("A")
    off = camera_pose(T_a[:3, 3], np.deg2rad(53.0), np.deg2rad(20.0))
    wide = PoseGate(base_pose(T_a), 0.3, np.radians(9.0))
    assert (
        prior_hypothesis(
            T_b, [off], Pairs(T_wi_a, out_a, CAMERA, config), wide, scale=1.0, averaging=averaging
        )
        is None
    )


def test_prior_pairs_place_the_query_in_the_room_the_robot_is_in() -> None:
    T_a, T_b, T_wi, out = _aliased_frame("AB")
    # Identical rooms: room B's pairs see the query as room A's do (relative poses at half scale).
    T_qi = np.array([invert_pose(T_a) @ T for T in T_wi[:3]] * 2)
    T_qi[:, :3, 3] *= 0.5
    out = replace(out, T_qi=T_qi)
    in_a = PoseGate(base_pose(T_a) + [0.1, 0.05, np.radians(3.0)], 0.25, np.radians(9.0))
    assert prior_pairs(T_wi, out, in_a).tolist() == [True] * 3 + [False] * 3
    in_b = PoseGate(base_pose(T_b), 0.25, np.radians(9.0))
    assert prior_pairs(T_wi, out, in_b).tolist() == [False] * 3 + [True] * 3
    turned = PoseGate(base_pose(T_a) + [0.0, 0.0, np.radians(20.0)], 0.25, np.radians(9.0))
    assert not prior_pairs(T_wi, out, turned).any()
    aside = PoseGate(base_pose(T_a) + [0.0, 1.0, 0.0], 0.25, np.radians(9.0))
    assert not prior_pairs(T_wi, out, aside).any()
    # The pairs the prior keeps average to room A's pose; all six give room B's (B's rays win the tie).
    kept = np.where(prior_pairs(T_wi, out, in_a), out.confidence, 0.0)
    motion = average_motion(T_wi, out.T_qi, kept)
    assert motion.ok and np.linalg.norm(motion.T_wq[:3, 3] - T_a[:3, 3]) < 1e-6
    assert np.linalg.norm(average_motion(T_wi, out.T_qi, out.confidence).T_wq[:3, 3] - T_b[:3, 3]) < 1e-3


def test_a_pose_inside_the_prior_needs_supporting_references_not_the_total_floor() -> None:
    T_a, T_b, T_wi, out = _aliased_frame("A")
    # Two references with 40 explained matches each: under min_total_support (140) without a prior.
    two = replace(
        out, T_qi=out.T_qi[:2], confidence=out.confidence[:2], n_matches=np.array([40, 40]),
        scale_valid=out.scale_valid[:2], matches=[m[:40] for m in out.matches[:2]],
    )  # fmt: skip
    config = VerifyConfig()
    alone = verify_pose(T_a, Pairs(T_wi[:2], two, CAMERA, config))
    assert alone.reason == "unverified" and alone.check == "support" and "only 80" in alone.detail
    prior = PoseGate(base_pose(T_a), 0.25, np.radians(9.0))
    placed = verify_pose(T_a, Pairs(T_wi[:2], two, CAMERA, config), prior=prior)
    assert placed.ok and placed.strength >= 75 and "inside the prior" in placed.detail and placed.by_prior
    # All references of the room: the images confirm the pose alone, the prior adds nothing.
    full = verify_pose(T_a, Pairs(T_wi, out, CAMERA, config), prior=prior)
    assert full.ok and not full.by_prior and verify_pose(T_a, Pairs(T_wi, out, CAMERA, config)).ok
    # One of them alone (under single_reference_support), or the camera rolled 3 deg (right poses:
    # < 0.5 deg), or outside the prior: unverified.
    one = replace(two, T_qi=two.T_qi[:1], confidence=two.confidence[:1], n_matches=two.n_matches[:1],
                  scale_valid=two.scale_valid[:1], matches=two.matches[:1])  # fmt: skip
    assert verify_pose(T_a, Pairs(T_wi[:1], one, CAMERA, config), prior=prior).check == "support"
    rolled = camera_pose(T_a[:3, 3], np.deg2rad(45.0), np.deg2rad(20.0), roll=np.deg2rad(3.0))
    assert verify_pose(rolled, Pairs(T_wi[:2], two, CAMERA, config), prior=prior).reason == "unverified"
    elsewhere = PoseGate(base_pose(T_a) + [0.5, 0.0, 0.0], 0.25, np.radians(9.0))
    assert verify_pose(T_a, Pairs(T_wi[:2], two, CAMERA, config), prior=elsewhere).check == "support"
    # The mount check stays: the camera 0.9 m too low is rejected inside the prior too.
    low = verify_pose(T_a, Pairs(T_wi[:2], two, CAMERA, config), prior=prior, camera_z=2.1)
    assert low.reason == "unverified" and low.check == "mount"


def test_pose_from_another_rooms_references_is_rejected() -> None:
    # The query's matches are with room A's references; a pose in room B explains none of them.
    T_a, T_b, T_wi, out = _aliased_frame("A")
    wrong = verify_pose(T_b, Pairs(T_wi, out, CAMERA, VerifyConfig()))
    assert not wrong.ok and wrong.reason == "unverified" and wrong.strength == 0 and wrong.confidence == 0
    assert wrong.check == "support"
    # A pose 0.5 m off in the right room explains (almost) nothing either.
    off = T_a.copy()
    off[:3, 3] += [0.5, -0.3, 0.0]
    assert verify_pose(off, Pairs(T_wi, out, CAMERA, VerifyConfig())).reason == "unverified"


def test_wrong_camera_height_or_tilt_is_rejected() -> None:
    T_a, _, T_wi, out = _aliased_frame("A")
    config = VerifyConfig(pose_height_tolerance=0.3)
    assert verify_pose(T_a, Pairs(T_wi, out, CAMERA, config), camera_z=1.1).ok  # 0.1 m high: within 0.3 m
    low = verify_pose(T_a, Pairs(T_wi, out, CAMERA, config), camera_z=2.1)
    assert (
        low.reason == "unverified" and low.detail == "camera height off by -0.90 m" and low.check == "mount"
    )
    rolled = camera_pose(T_a[:3, 3], np.deg2rad(45.0), np.deg2rad(20.0), roll=np.deg2rad(12.0))
    assert "rolled" in verify_pose(rolled, Pairs(T_wi, out, CAMERA, config)).detail
    level = camera_pose(T_a[:3, 3], np.deg2rad(45.0), np.deg2rad(-20.0))  # looking up
    assert "pitched" in verify_pose(level, Pairs(T_wi, out, CAMERA, config)).detail


def test_epipolar_support_counts_the_matches_a_pose_explains() -> None:
    T_a, _, T_wi, out = _aliased_frame("A")
    support = epipolar_support(T_a, T_wi, out.matches, CAMERA, 2.0)
    assert (support >= 0.95 * out.n_matches).all()  # 0.3 px noise: nearly all within 2 px
    turned = camera_pose(T_a[:3, 3], np.deg2rad(55.0), np.deg2rad(20.0))  # 10 deg of yaw off
    assert (epipolar_support(turned, T_wi, out.matches, CAMERA, 2.0) < 0.2 * out.n_matches).all()
    with pytest.raises(ValueError, match="match arrays"):
        epipolar_support(T_a, T_wi[:2], out.matches, CAMERA, 2.0)


def test_epipolar_support_of_stacked_poses_equals_one_pose_at_a_time() -> None:
    """A grid of poses (a prior placement's search), a pure rotation among them: the same counts."""
    T_a, _, T_wi, out = _aliased_frame("A")
    poses = [camera_pose(T_a[:3, 3] + [dx, dy, 0.0], np.deg2rad(45.0 + yaw), np.deg2rad(20.0))
             for dx in (-0.2, 0.0, 0.1) for dy in (-0.1, 0.0) for yaw in (0.0, 3.0)]  # fmt: skip
    poses.append(T_wi[0] @ make_pose(Rotation.from_euler("y", 10, degrees=True), [0.0, 0.0, 0.0]))
    stacked = epipolar_support(np.stack(poses), T_wi, out.matches, CAMERA, 2.0)
    one_by_one = np.stack([epipolar_support(T, T_wi, out.matches, CAMERA, 2.0) for T in poses])
    assert stacked.shape == (len(poses), len(T_wi)) and (stacked == one_by_one).all()
    assert stacked.max() >= 0.95 * out.n_matches.max()  # not all zero: the true pose is in the grid
    m = np.asarray(out.matches[1], float)
    K_inv = np.linalg.inv(CAMERA.K)
    x_q, x_r = np.c_[m[:, :2], np.ones(len(m))] @ K_inv.T, np.c_[m[:, 2:], np.ones(len(m))] @ K_inv.T
    behind = camera_pose(T_a[:3, 3], np.deg2rad(225.0), np.deg2rad(20.0))  # faces away
    T_iq = invert_pose(T_wi[1]) @ np.stack([*poses, behind])
    front = in_front_of_both(x_q, x_r, T_iq[:, :3, :3], T_iq[:, :3, 3])
    each = [triangulate_query_depth(x_q, x_r, T[:3, :3], T[:3, 3])[2] for T in T_iq]
    assert (front == np.stack(each)).all() and front.any() and not front.all()


def _wallpaper_frame():
    """(true T_wq, the same pose in room B, room A's output, room B's output): room A's references
    match the query on two walls and the floor; room B's (the same cameras moved by SHIFT) match
    it only on one wall whose texture room B repeats, so those matches fit the pose in room B."""
    rng = np.random.default_rng(1)
    points = _room_points(rng)
    wall = np.c_[np.full(2400, 4.0), rng.uniform(0, 4, 2400), rng.uniform(0, 2.5, 2400)]  # the x = 4 wall
    T_q = camera_pose([1.0, 1.2, 1.2], np.deg2rad(45.0), np.deg2rad(20.0))
    refs = [camera_pose([x, y, 1.5], np.deg2rad(yaw), np.deg2rad(25.0)) for x, y, yaw in
            [(0.6, 1.5, 40.0), (1.5, 0.5, 55.0), (1.2, 1.9, 35.0)]]  # fmt: skip

    def output(matches: list[np.ndarray]) -> BackboneOutput:
        k = len(matches)
        return BackboneOutput(
            np.tile(np.eye(4), (k, 1, 1)), np.full(k, 0.5), np.array([len(m) for m in matches]),
            np.zeros((2, 2), np.float32), np.zeros((2, 2), np.float32), "test", "none", matches=matches,
        )  # fmt: skip

    T_b = T_q.copy()
    T_b[:3, 3] += SHIFT
    out_a = output([_matches(T_q, T, points, rng) for T in refs])
    out_b = output([_matches(T_q, T, wall, rng) for T in refs])
    return T_q, T_b, np.array(refs), out_a, out_b


def test_off_plane_support_rejects_a_place_that_only_repeats_a_walls_texture() -> None:
    T_a, T_b, T_wi_a, out_a, out_b = _wallpaper_frame()
    T_wi_b = T_wi_a.copy()
    T_wi_b[:, :3, 3] += SHIFT
    counting_all, plane = VerifyConfig(plane_threshold_px=None), VerifyConfig(plane_threshold_px=2.0)
    # Counting every match, room B's wall texture confirms the wrong room as well as room A does.
    assert verify_pose(T_b, Pairs(T_wi_b, out_b, CAMERA, counting_all)).ok
    # Off the dominant plane nothing is left of room B's matches: unverified.
    flat = off_plane_matches(out_b, 2.0)
    assert all(len(m) <= 0.05 * n for m, n in zip(flat.matches, out_b.n_matches, strict=True))
    wrong = verify_pose(T_b, Pairs(T_wi_b, out_b, CAMERA, plane))
    assert not wrong.ok and wrong.reason == "unverified" and "dominant planes" in wrong.detail
    assert wrong.check == "plane"
    # Room A's references see two walls and the floor: matches stay off the dominant plane.
    kept = np.array([len(m) for m in off_plane_matches(out_a, 2.0).matches])
    assert ((kept >= 0.2 * out_a.n_matches) & (kept <= 0.8 * out_a.n_matches)).all()
    right = verify_pose(T_a, Pairs(T_wi_a, out_a, CAMERA, plane))
    assert right.ok and right.n_supporting == 3 and right.confidence > 0.8
    # Both rooms' references: room B's wall makes a rival as strong as the pose (ambiguous when
    # every match counts); off the plane it is no place, and the right room is kept.
    both = replace(out_a, T_qi=np.tile(np.eye(4), (6, 1, 1)), confidence=np.full(6, 0.5),
                   n_matches=np.r_[out_a.n_matches, out_b.n_matches], matches=out_a.matches + out_b.matches,
                   scale_valid=None)  # fmt: skip
    T_wi = np.concatenate([T_wi_a, T_wi_b])
    assert verify_pose(T_a, Pairs(T_wi, both, CAMERA, counting_all), rivals=[T_b]).reason == "ambiguous"
    kept_right = verify_pose(T_a, Pairs(T_wi, both, CAMERA, plane), rivals=[T_b])
    assert kept_right.ok and kept_right.rival_strength == 0 and kept_right.support[:3].all()
    # A pair under 8 matches keeps none; an output without matches is returned unchanged.
    few = off_plane_matches(replace(out_a, matches=[m[:7] for m in out_a.matches]), 2.0)
    assert all(len(m) == 0 for m in few.matches)
    no_matches = replace(out_a, matches=None)
    assert off_plane_matches(no_matches, 2.0) is no_matches
    with pytest.raises(ValueError, match="plane_threshold_px"):
        VerifyConfig(plane_threshold_px=0.0)


def test_one_reference_confirms_a_place_only_with_single_reference_support_matches() -> None:
    T_a, T_b, T_wi, out = _aliased_frame("AB")
    # Two of room A's references and one of room B's: one pair of B explains B's pose in full.
    keep = [0, 1, 3]
    out = replace(
        out, T_qi=out.T_qi[keep], confidence=out.confidence[keep], n_matches=out.n_matches[keep],
        scale_valid=out.scale_valid[keep], matches=[out.matches[i] for i in keep],
    )  # fmt: skip
    T_wi = T_wi[keep]
    lone = int(epipolar_support(T_b, T_wi[2:], out.matches[2:], CAMERA, 2.0)[0])
    assert lone >= 100
    # As a rival, the lone pair of room B (half of A's two pairs) makes room A's pose ambiguous...
    config = VerifyConfig(single_reference_support=lone, ambiguity_ratio=0.4)
    verdict = verify_pose(T_a, Pairs(T_wi, out, CAMERA, config), rivals=[T_b])
    assert verdict.reason == "ambiguous" and verdict.rival_strength == lone, verdict.detail
    # ...but not when one reference must explain more than it does (nor without the rule).
    for single in (lone + 1, None):
        verdict = verify_pose(
            T_a, Pairs(T_wi, out, CAMERA, VerifyConfig(single_reference_support=single)), rivals=[T_b]
        )
        assert verdict.ok and verdict.rival_strength == 0, verdict.detail
    # As the pose, B's single pair confirms it only with single_reference_support matches (with
    # the explained-confidence gate off: A's two pairs, as confident, do not explain it)...
    free = VerifyConfig(single_reference_support=lone, min_explained_confidence=None)
    alone = verify_pose(T_b, Pairs(T_wi, out, CAMERA, free))
    assert alone.ok and alone.n_supporting == 1 and alone.strength == lone
    for single in (lone + 1, None):
        alone = verify_pose(T_b, Pairs(T_wi, out, CAMERA, replace(free, single_reference_support=single)))
        assert alone.reason == "unverified" and "1 reference(s)" in alone.detail
    # ...and the gate rejects it: one third of the pairs' confidence.
    gated = verify_pose(T_b, Pairs(T_wi, out, CAMERA, VerifyConfig(single_reference_support=lone)))
    assert gated.reason == "unverified" and "33% of the pairs' confidence" in gated.detail


def test_a_pose_the_most_confident_pairs_do_not_explain_is_rejected() -> None:
    T_a, T_b, T_wi, out = _aliased_frame("AB")
    # Each pair's own geometry is the true one (room B's references see room A's view from their
    # camera); room A's pairs are confident (0.9), room B's weak (0.2).
    T_qi = invert_pose(T_a) @ np.concatenate([T_wi[:3], T_wi[:3]])
    out = replace(out, T_qi=T_qi, confidence=np.r_[np.full(3, 0.9), np.full(3, 0.2)])
    config = VerifyConfig()
    assert config.min_explained_confidence == 0.45
    # Room A's pose explains room A's pairs in full: 3 x 0.9 of 3.3; room B's pose only B's pairs.
    assert explained_confidence(T_a, Pairs(T_wi, out, CAMERA, config)) == pytest.approx(2.7 / 3.3, abs=0.03)
    assert explained_confidence(T_b, Pairs(T_wi, out, CAMERA, config)) == pytest.approx(0.6 / 3.3, abs=0.03)
    assert verify_pose(T_a, Pairs(T_wi, out, CAMERA, config)).ok
    # Room B's weak pairs alone confirm its pose, but the confident pairs see another place.
    wrong = verify_pose(T_b, Pairs(T_wi, out, CAMERA, config))
    assert not wrong.ok and wrong.reason == "unverified" and "18% of the pairs' confidence" in wrong.detail
    assert wrong.check == "share" and verify_pose(T_a, Pairs(T_wi, out, CAMERA, config)).check == ""
    assert verify_pose(T_b, Pairs(T_wi, out, CAMERA, replace(config, min_explained_confidence=None))).ok
    # A pair counts by the share of its own geometry's matches the pose explains: a pose 10 deg
    # of yaw off keeps few of room A's matches.
    turned = camera_pose(T_a[:3, 3], np.deg2rad(55.0), np.deg2rad(20.0))
    assert explained_confidence(turned, Pairs(T_wi[:3], replace_first(out, 3), CAMERA, config)) < 0.2
    assert explained_confidence(T_a, Pairs(T_wi, replace(out, confidence=np.zeros(6)), CAMERA, config)) == 0.0
    with pytest.raises(ValueError, match="min_explained_confidence"):
        VerifyConfig(min_explained_confidence=0.0)


def replace_first(out: BackboneOutput, k: int) -> BackboneOutput:
    """``out`` restricted to its first ``k`` pairs."""
    return replace(
        out, T_qi=out.T_qi[:k], confidence=out.confidence[:k], n_matches=out.n_matches[:k],
        scale_valid=out.scale_valid[:k], matches=out.matches[:k],
    )  # fmt: skip


def test_a_reference_the_pose_explains_in_small_part_still_makes_a_rival() -> None:
    # Room B's pose with one of B's references and one of A's: A's pair sees room A's view (its
    # own geometry is the true pose), and 40 of its matches (far points, in front of both
    # cameras) happen to fit B's pose too: B's pose "explains" A's reference, in small part.
    T_a, T_b, T_wi, out = _aliased_frame("AB")
    keep = [3, 0]
    rng = np.random.default_rng(2)
    far = np.c_[rng.uniform(25, 60, 4000), rng.uniform(25, 60, 4000), rng.uniform(0, 3, 4000)]
    stray = _matches(T_b, T_wi[0], far, rng)[:40]
    assert len(stray) == 40
    matches = [out.matches[3], np.concatenate([out.matches[0], stray])]
    T_wi = T_wi[keep]
    out = replace(
        out, T_qi=invert_pose(T_a) @ T_wi, confidence=np.full(2, 0.5),
        n_matches=np.array([len(m) for m in matches]), scale_valid=out.scale_valid[keep], matches=matches,
    )  # fmt: skip
    config = VerifyConfig(min_explained_confidence=None)
    raw = epipolar_support(T_b, T_wi, out.matches, CAMERA, 2.0)
    own = pair_support(Pairs(T_wi, out, CAMERA, config))
    assert raw[1] >= 38 and own[1] >= 5 * raw[1], (raw, own)
    # Unexplained references only (the rule before rival_claim_ratio): room A is no rival, and the
    # wrong room is confirmed by two references.
    old = replace(config, rival_claim_ratio=None)
    assert verify_pose(T_b, Pairs(T_wi, out, CAMERA, old), rivals=[T_a]).ok
    assert rival_pairs(raw, Pairs(T_wi, out, CAMERA, old)).tolist() == raw.tolist()
    # A's pair, explained by B's pose in under half of what room A's pose explains, is room A's:
    # rival_poses gets it as a pair the pose does not explain, and the frame is ambiguous.
    assert rival_pairs(raw, Pairs(T_wi, out, CAMERA, config)).tolist() == [raw[0], 0]
    verdict = verify_pose(T_b, Pairs(T_wi, out, CAMERA, config), rivals=[T_a])
    assert verdict.reason == "ambiguous" and verdict.rival_strength >= own[1] - 5, verdict.detail
    # Room A's pose is ambiguous too (room B's reference), never confirmed as the only place.
    assert verify_pose(T_a, Pairs(T_wi, out, CAMERA, config), rivals=[T_b]).reason == "ambiguous"
    with pytest.raises(ValueError, match="rival_claim_ratio"):
        VerifyConfig(rival_claim_ratio=1.5)


def test_ambiguity_compares_the_strongest_references_of_each_place() -> None:
    # Room B's pose has its three references; room A, the true room, has one view retrieved (all
    # of a place's views match the query alike in identical rooms).
    T_a, T_b, T_wi, out = _aliased_frame("AB")
    keep = [3, 4, 5, 0]
    out = replace(
        out, T_qi=out.T_qi[keep], confidence=out.confidence[keep], n_matches=out.n_matches[keep],
        scale_valid=out.scale_valid[keep], matches=[out.matches[i] for i in keep],
    )  # fmt: skip
    T_wi = T_wi[keep]
    summed = VerifyConfig(
        ambiguity_references=None,
        min_explained_confidence=None,
        ambiguity_ratio=0.45,
        rival_confidence_ratio=None,
    )
    # Summed over all references, three views of B (664, 670, 530 matches) outweigh A's one
    # (664): B is confirmed, wrongly (without rival_confidence_ratio: A's pair is as confident).
    assert verify_pose(T_b, Pairs(T_wi, out, CAMERA, summed), rivals=[T_a]).ok
    # The two strongest references of each place: A's lone view against B's two, ambiguous.
    verdict = verify_pose(
        T_b, Pairs(T_wi, out, CAMERA, replace(summed, ambiguity_references=2)), rivals=[T_a]
    )
    assert verdict.reason == "ambiguous", verdict.detail
    assert VerifyConfig().ambiguity_references == 2
    with pytest.raises(ValueError, match="ambiguity_references"):
        VerifyConfig(ambiguity_references=0)


def test_the_losing_rounds_pairs_still_count() -> None:
    # Round 1 retrieved room A's references (the query's room); round 2 chose references around a
    # hypothesis in room B and won. Round 2's pairs alone confirm room B; pooled with round 1's,
    # room A is a rival as strong: ambiguous, never the wrong room.
    T_a, T_b, T_wi, out = _aliased_frame("AB")
    first, second = replace_first(out, 3), _last(out, 3)
    refs_1, refs_2 = np.array([10, 11, 12]), np.array([20, 21, 22])
    config = VerifyConfig(min_explained_confidence=None)
    assert verify_pose(T_b, Pairs(T_wi[3:], second, CAMERA, config), rivals=[T_a]).ok
    refs, pooled = pooled_pairs(refs_2, second, refs_1, first)
    assert refs.tolist() == [20, 21, 22, 10, 11, 12] and pooled.k == 6
    assert [len(m) for m in pooled.matches] == [len(m) for m in second.matches + first.matches]
    T_pooled = np.concatenate([T_wi[3:], T_wi[:3]])
    verdict = verify_pose(T_b, Pairs(T_pooled, pooled, CAMERA, config), rivals=[T_a])
    assert verdict.reason == "ambiguous", verdict.detail
    # A reference both rounds used counts once.
    refs, pooled = pooled_pairs(refs_2, second, np.array([20, 10]), replace_first(first, 2))
    assert refs.tolist() == [20, 21, 22, 10] and pooled.k == 4
    assert pooled_pairs(refs_2, second, refs_2, second)[1] is second


def _last(out: BackboneOutput, k: int) -> BackboneOutput:
    """``out`` restricted to its last ``k`` pairs."""
    return replace(
        out, T_qi=out.T_qi[-k:], confidence=out.confidence[-k:], n_matches=out.n_matches[-k:],
        scale_valid=out.scale_valid[-k:], matches=out.matches[-k:],
    )  # fmt: skip


def test_a_rival_does_not_change_the_share_the_pose_explains() -> None:
    # A pose 2 deg of yaw off explains part of each pair's matches: 32 % of the pairs' confidence,
    # under 45 %. A distinct rival the images do not support leaves that share as it is (the pairs'
    # own support is theirs, never a rival's reference mask).
    T_a, _, T_wi, out = _aliased_frame("A")
    out = replace(out, T_qi=invert_pose(T_a) @ T_wi)
    config = VerifyConfig()
    pairs = Pairs(T_wi, out, CAMERA, config)
    turned = camera_pose(T_a[:3, 3], np.deg2rad(47.0), np.deg2rad(20.0))
    far = camera_pose([5.0, 5.0, 1.2], 0.0, np.deg2rad(20.0))
    alone = verify_pose(turned, pairs)
    with_rival = verify_pose(turned, pairs, rivals=[far])
    assert alone.check == with_rival.check == "share", with_rival.detail
    assert with_rival.detail == alone.detail == "the pose explains 32% of the pairs' confidence"


def test_a_pose_two_references_barely_explain_is_rejected() -> None:
    # Room A's pose explained by two references with 60 matches each: each is over
    # min_support_matches, but 120 matches together are under the total floor.
    # (every k-th match: walls and floor alike, so off-plane matches remain)
    T_a, _, T_wi, out = _aliased_frame("A")
    keep = [0, 1]
    spread = [out.matches[i][np.linspace(0, len(out.matches[i]) - 1, 60).astype(int)] for i in keep]
    few = replace(
        out, T_qi=out.T_qi[keep], confidence=out.confidence[keep], n_matches=np.full(2, 60),
        scale_valid=out.scale_valid[keep], matches=spread,
    )  # fmt: skip
    T_wi = T_wi[keep]
    free = verify_pose(T_a, Pairs(T_wi, few, CAMERA, VerifyConfig(min_total_support=None)))
    assert free.ok and free.n_supporting == 2 and 110 <= free.strength <= 120, free.detail
    weak = verify_pose(T_a, Pairs(T_wi, few, CAMERA, VerifyConfig(min_total_support=140)))
    assert not weak.ok and weak.reason == "unverified" and weak.check == "support", weak.detail
    assert weak.detail == f"2 references explain only {free.strength} matches"
    # With all their matches the same two references confirm the pose.
    full = replace(few, n_matches=out.n_matches[keep], matches=[out.matches[i] for i in keep])
    assert verify_pose(T_a, Pairs(T_wi, full, CAMERA, VerifyConfig(min_total_support=140))).ok
    with pytest.raises(ValueError, match="min_total_support"):
        VerifyConfig(min_total_support=0)


def _errors(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(metres, degrees) between two camera poses."""
    R = T[:3, :3].T @ T_true[:3, :3]
    angle = np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))
    return float(np.linalg.norm(T[:3, 3] - T_true[:3, 3])), float(angle)


def test_refine_pose_moves_a_nearby_pose_onto_the_one_the_matches_fit() -> None:
    T_a, _, T_wi, out = _aliased_frame("A")
    config = VerifyConfig()
    # 8 cm and 1.2 deg of yaw off (inside the 1.5 deg bound): each reference explains fewer matches.
    start = camera_pose(T_a[:3, 3] + [0.06, -0.05, 0.02], np.deg2rad(46.2), np.deg2rad(20.0))
    before = epipolar_support(start, T_wi, out.matches, CAMERA, config.max_epipolar_error_px)
    pairs = Pairs(T_wi, out, CAMERA, config)
    refined = refine_pose(start, pairs, max_shift=0.25)
    after = epipolar_support(refined, T_wi, out.matches, CAMERA, config.max_epipolar_error_px)
    dt, dr = _errors(refined, T_a)
    assert dt < 0.005 and dr < 0.05, (dt, dr)
    assert (after >= 0.95 * out.n_matches).all() and (before < after).all(), (before, after)
    # The refinement stays within its bounds: 0.3 m away it moves at most max_shift per axis.
    far = start.copy()
    far[0, 3] += 0.3
    bounded = refine_pose(far, pairs, max_shift=0.1)
    assert np.abs(bounded[:2, 3] - far[:2, 3]).max() <= 0.1 + 1e-9
    one_each = Pairs(T_wi, replace(out, matches=[m[:1] for m in out.matches]), CAMERA, config)
    assert refine_pose(start, one_each, max_shift=0.1) is start


def test_prior_poses_place_the_query_when_the_pairs_translations_are_wrong() -> None:
    """Short baselines: the pairs' rotations are right but their translation directions 60 deg off, so
    no two rays meet at the query. Inside a prior 5 cm / 2 deg from the truth, the pairs' rotations
    at the position the matches fit best are the query's pose, confirmed by all three references; a
    prior in the other room gives poses no reference confirms."""
    T_a, T_b, T_wi, out = _aliased_frame("A")
    config = VerifyConfig()
    T_qi = np.array([invert_pose(T_a) @ T for T in T_wi])
    turn = Rotation.from_euler("y", 60.0, degrees=True).as_matrix()
    T_qi[:, :3, 3] = T_qi[:, :3, 3] @ turn.T
    out = replace(out, T_qi=T_qi)
    prior = PoseGate(base_pose(T_a) + [0.04, -0.03, np.radians(2.0)], 0.25, np.radians(9.0))
    hypotheses = prior_poses(Pairs(T_wi, out, CAMERA, config), prior, T_a[2, 3], RecoveryConfig())
    assert len(hypotheses) == 1  # the three pairs' rotations are one
    placed = refine_pose(hypotheses[0], Pairs(T_wi, out, CAMERA, config), max_shift=prior.max_distance)
    dt, dr = _errors(placed, T_a)
    assert dt < 0.01 and dr < 0.1, (dt, dr)
    verdict = verify_pose(placed, Pairs(T_wi, out, CAMERA, config), camera_z=T_a[2, 3], prior=prior)
    assert verdict.ok and verdict.n_supporting == 3, verdict.detail
    # Expected in room B (whose references were not retrieved): the poses there explain nothing.
    in_b = PoseGate(base_pose(T_b) + [0.04, -0.03, np.radians(2.0)], 0.25, np.radians(9.0))
    in_room_b = prior_poses(Pairs(T_wi, out, CAMERA, config), in_b, T_b[2, 3], RecoveryConfig())
    assert len(in_room_b) == 1
    for T in [*in_room_b, refine_pose(in_room_b[0], Pairs(T_wi, out, CAMERA, config), max_shift=0.25)]:
        assert not verify_pose(T, Pairs(T_wi, out, CAMERA, config), camera_z=T_b[2, 3], prior=in_b).ok
    # A pair turned outside the prior's yaw bound, or rolled, gives no hypothesis.
    turned = PoseGate(base_pose(T_a) + [0.0, 0.0, np.radians(15.0)], 0.25, np.radians(9.0))
    assert prior_poses(Pairs(T_wi, out, CAMERA, config), turned, T_a[2, 3], RecoveryConfig()) == []


def test_slide_on_ray_moves_a_pose_placed_at_the_wrong_scale_to_where_the_references_see_it() -> None:
    """The first pair's ray is right but its scale 25 % long: the other references' matches put the
    query back on the truth, and the factor says how far the scale was off. A right pose, a position
    several rays carry, a truth out of reach or the slide switched off move nothing."""
    T_a, _, T_wi, out = _aliased_frame("A")
    config = VerifyConfig()
    T_qi = np.array([invert_pose(T_a) @ T for T in T_wi])
    out = replace(out, T_qi=T_qi)
    centre = T_wi[0][:3, 3]
    far = T_a.copy()
    far[:3, 3] = centre + 1.25 * (T_a[:3, 3] - centre)
    weights = np.array([1.0, 0.1, 0.0])
    pairs, recovery = Pairs(T_wi, out, CAMERA, config), RecoveryConfig()
    moved, factor = slide_on_ray(far, pairs, weights, recovery)
    dt, dr = _errors(moved, T_a)
    assert dt < 0.005 and dr < 1e-3, (dt, dr)
    assert factor == pytest.approx(1 / 1.25, rel=0.01)
    assert slide_on_ray(T_a, pairs, weights, recovery) is None
    assert slide_on_ray(far, pairs, np.array([1.0, 1.0, 0.5]), recovery) is None
    assert slide_on_ray(far, pairs, weights, replace(recovery, ray_slide_share=None)) is None
    # The truth 0.145 m away along the ray, beyond a 0.1 m reach: never moved more than the reach.
    bounded = slide_on_ray(far, pairs, weights, replace(recovery, ray_slide_max_shift=0.1))
    assert bounded is None or np.linalg.norm(bounded[0][:3, 3] - far[:3, 3]) <= 0.1 + 1e-9
    with pytest.raises(ValueError, match="ray_slide_share"):
        RecoveryConfig(ray_slide_share=0.0)


def test_slide_on_ray_needs_the_other_references_to_support_the_new_place() -> None:
    """A right pose that one pair carries stays where it is when the other references explain fewer
    than ``min_support_matches`` matches anywhere on the ray (a handful of stray matches would peak
    somewhere along the ray and move a right pose there). With the matches of a real reference the
    pose placed at a wrong scale still moves."""
    T_a, _, T_wi, out = _aliased_frame("A")
    config = VerifyConfig()
    out = replace(out, T_qi=np.array([invert_pose(T_a) @ T for T in T_wi]))
    centre = T_wi[0][:3, 3]
    far = T_a.copy()
    far[:3, 3] = centre + 1.25 * (T_a[:3, 3] - centre)
    weights = np.array([1.0, 0.1, 0.0])
    few = replace(out, matches=[out.matches[0], out.matches[1][:12], out.matches[2][:12]])
    assert epipolar_support(T_a, T_wi[1:], few.matches[1:], CAMERA, config.max_epipolar_error_px).sum() >= 20
    recovery = RecoveryConfig()
    assert slide_on_ray(far, Pairs(T_wi, few, CAMERA, config), weights, recovery) is None
    assert slide_on_ray(T_a, Pairs(T_wi, few, CAMERA, config), weights, recovery) is None
    moved = slide_on_ray(far, Pairs(T_wi, out, CAMERA, config), weights, recovery)
    assert moved is not None and _errors(moved[0], T_a)[0] < 0.005


def test_the_support_a_pose_placed_inside_a_prior_needs_grows_with_the_prior() -> None:
    """``prior_support_per_m`` per metre of the prior's radius, never above the floor without a
    prior (``min_total_support``): 67 matches inside the tightest prior the EKF gives (0.19 m, a
    fix's gate), 140 (the floor) at its widest (0.4 m)."""
    config, recovery = VerifyConfig(), RecoveryConfig()
    assert config.min_total_support == 140 and recovery.prior_support_per_m == 350.0
    assert prior_support_floor(PoseGate(np.zeros(3), 0.19, 0.2), config, recovery) == 67
    assert prior_support_floor(PoseGate(np.zeros(3), 0.4, 0.2), config, recovery) == 140
    assert prior_support_floor(PoseGate(np.zeros(3), 1.0, 0.2), config, recovery) == 140
    off = replace(recovery, prior_support_per_m=None)
    assert prior_support_floor(PoseGate(np.zeros(3), 0.19, 0.2), config, off) == 140
    with pytest.raises(ValueError, match="prior_support_per_m"):
        RecoveryConfig(prior_support_per_m=0.0)
