"""Classical backbone on analytic views of a textured room corner (exact poses and depth)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from backbone_synthetic import render_corner

from vgpnav_env.geometry import PinholeCamera, invert_pose, rotation_angle
from vgpnav_env.perception.backbones import ClassicalBackbone, ClassicalConfig, FeatureCache, make_backbone
from vgpnav_env.perception.backbones.classical import (
    link_scales,
    match_descriptors,
    refine_matches,
    sampson_distance,
)

CAMERA = PinholeCamera(320, 240, np.deg2rad(60.0))
K_REFS = 5


@pytest.fixture(scope="module")
def scene():
    query, query_depth, refs, T_wq, T_wi = render_corner(CAMERA, K_REFS, seed=3)
    return {"T_qi": invert_pose(T_wq) @ T_wi, "query": query, "depth": query_depth, "refs": refs}


@pytest.fixture(scope="module")
def result(scene):
    backbone = ClassicalBackbone()
    out = backbone(scene["query"], scene["refs"], CAMERA, reference_keys=list(range(K_REFS)))
    return backbone, out


def direction_error_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = a @ b / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def test_relative_poses_are_accurate(scene, result):
    _, out = result
    assert out.name == "classical" and out.scale == "median_query_depth"
    assert out.T_qi.shape == (K_REFS, 4, 4)
    assert np.all(out.confidence > 0.5) and np.all(out.n_matches >= 50)
    for i in range(K_REFS):
        rot_err = np.degrees(rotation_angle(out.T_qi[i, :3, :3], scene["T_qi"][i, :3, :3]))
        dir_err = direction_error_deg(out.T_qi[i, :3, 3], scene["T_qi"][i, :3, 3])
        assert rot_err < 0.5, (i, rot_err)
        assert dir_err < 2.0, (i, dir_err)
    np.testing.assert_allclose(out.T_iq @ out.T_qi, np.tile(np.eye(4), (K_REFS, 1, 1)), atol=1e-9)
    np.testing.assert_allclose(out.R_iq, np.swapaxes(out.T_qi[:, :3, :3], 1, 2))


def test_one_common_scale_across_references(scene, result):
    _, out = result
    assert out.scale_valid.all()
    ratios = np.linalg.norm(out.T_qi[:, :3, 3], axis=1) / np.linalg.norm(scene["T_qi"][:, :3, 3], axis=1)
    assert np.all(np.abs(ratios / np.median(ratios) - 1.0) < 0.05), ratios


def test_plane_sweep_depth_matches_truth_at_the_common_scale(scene, result):
    _, out = result
    assert out.query_depth.shape == (240, 320) and out.query_depth.dtype == np.float32
    assert out.query_depth_confidence.min() >= 0 and out.query_depth_confidence.max() <= 1
    scale = np.median(
        np.linalg.norm(out.T_qi[:, :3, 3], axis=1) / np.linalg.norm(scene["T_qi"][:, :3, 3], axis=1)
    )
    confident = out.query_depth_confidence > 0.5
    assert confident.mean() > 0.3
    rel = np.abs(out.query_depth[confident] / scale - scene["depth"][confident]) / scene["depth"][confident]
    assert np.median(rel) < 0.05
    # The scale convention: the confident dense depths have a median near 1.
    assert 0.7 < np.median(out.query_depth[confident]) < 1.4


def test_reference_features_are_cached_by_key(scene, result):
    backbone, out = result
    assert len(backbone.feature_cache) == K_REFS
    again = backbone(scene["query"], scene["refs"], CAMERA, reference_keys=list(range(K_REFS)))
    np.testing.assert_allclose(again.T_qi, out.T_qi, atol=1e-6)
    cache = FeatureCache(max_items=2)
    for key in "abc":
        cache.put(key, backbone.feature_cache.get(0))
    assert len(cache) == 2 and "a" not in cache and "c" in cache


def test_pairs_only_skip_the_sweep_and_keep_the_pairs(scene, result):
    _, out = result
    pairs = ClassicalBackbone()(
        scene["query"], scene["refs"], CAMERA, reference_keys=list(range(K_REFS)), depth=False
    )
    np.testing.assert_array_equal(pairs.T_qi, out.T_qi)
    np.testing.assert_array_equal(pairs.confidence, out.confidence)
    np.testing.assert_array_equal(pairs.scale_valid, out.scale_valid)
    assert out.query_depth.any() and not pairs.query_depth.any()


def test_black_query_and_unrelated_reference_fail_softly(scene):
    backbone = make_backbone("classical")
    black = np.zeros_like(scene["query"])
    out = backbone(black, scene["refs"][:3], CAMERA)
    assert np.all(out.confidence == 0) and not out.scale_valid.any()
    assert np.all(out.query_depth_confidence == 0)
    noise = np.random.default_rng(0).integers(0, 256, scene["query"].shape, dtype=np.uint8)
    out = backbone(scene["query"], [noise, scene["refs"][0]], CAMERA)
    assert out.confidence[0] == 0 and out.confidence[1] > 0.5
    out = backbone(scene["query"], [], CAMERA)
    assert out.T_qi.shape == (0, 4, 4) and np.all(out.query_depth_confidence == 0)


def test_bad_inputs_are_rejected(scene):
    backbone = ClassicalBackbone()
    with pytest.raises(ValueError, match="uint8"):
        backbone(scene["query"].astype(np.float32), scene["refs"], CAMERA)
    with pytest.raises(ValueError, match="reference_keys"):
        backbone(scene["query"], scene["refs"], CAMERA, reference_keys=[0])
    with pytest.raises(ValueError, match="ratio"):
        ClassicalConfig(ratio=1.5)


def test_matching_and_scale_linking_units():
    rng = np.random.default_rng(0)
    a = rng.standard_normal((50, 128)).astype(np.float32)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    perm = rng.permutation(50)
    matches = match_descriptors(a, a[perm], ratio=0.8, mutual=True)
    assert len(matches) == 50
    np.testing.assert_array_equal(perm[matches[:, 1]], matches[:, 0])

    class Pair:
        def __init__(self, index, depth, n_inliers):
            self.query_index, self.depth, self.n_inliers = (
                np.asarray(index),
                np.asarray(depth, float),
                n_inliers,
            )

    depth = rng.uniform(1, 3, 30)
    pairs = [Pair(np.arange(20), depth[:20] * 2.0, 100), Pair(np.arange(10, 30), depth[10:] * 0.5, 90), None]
    pairs.append(Pair(np.arange(40, 60), np.ones(20), 300))
    scales, linked = link_scales(pairs, min_common=8)
    np.testing.assert_array_equal(linked, [False, False, False, True])
    pairs[3] = Pair(np.arange(40, 50), np.ones(10), 10)
    scales, linked = link_scales(pairs, min_common=8)
    np.testing.assert_array_equal(linked, [True, True, False, False])
    assert scales[0] * 2.0 == pytest.approx(scales[1] * 0.5)
    # A pair whose shared depths disagree (a wrong relative pose) is not linked.
    pairs[2] = Pair(np.arange(20), depth[:20] * np.geomspace(0.2, 5.0, 20), 50)
    scales, linked = link_scales(pairs, min_common=8, max_spread=0.15)
    np.testing.assert_array_equal(linked, [True, True, False, False])


def test_threads_do_not_change_the_result(scene, result):
    _, out = result
    threaded = ClassicalBackbone(ClassicalConfig(threads=2))
    serial = ClassicalBackbone(ClassicalConfig(threads=1))
    keys = list(range(K_REFS))
    for backbone in (threaded, serial):
        again = backbone(scene["query"], scene["refs"], CAMERA, reference_keys=keys)
        np.testing.assert_array_equal(again.T_qi, out.T_qi)
        np.testing.assert_array_equal(again.confidence, out.confidence)
        np.testing.assert_array_equal(again.query_depth, out.query_depth)
        np.testing.assert_array_equal(again.query_depth_confidence, out.query_depth_confidence)
    with pytest.raises(ValueError, match="threads"):
        ClassicalConfig(threads=-1)


def test_a_second_call_on_the_same_query_reuses_its_features_and_pairs(scene, monkeypatch):
    backbone = ClassicalBackbone()
    calls = []
    original = ClassicalBackbone.relative_pose

    def counting(self, fq, fr, camera, expected_T_iq=None, matches=None, images=None):
        calls.append(fr)
        return original(self, fq, fr, camera, expected_T_iq, matches, images)

    monkeypatch.setattr(ClassicalBackbone, "relative_pose", counting)
    first = backbone(scene["query"], scene["refs"][:3], CAMERA, reference_keys=[0, 1, 2])
    assert len(calls) == 3
    second = backbone(scene["query"], scene["refs"][1:], CAMERA, reference_keys=[1, 2, 3, 4])
    assert len(calls) == 5  # only references 3 and 4 are new
    np.testing.assert_array_equal(second.T_qi[:2, :3, :3], first.T_qi[1:, :3, :3])
    fresh = ClassicalBackbone()(scene["query"], scene["refs"][1:], CAMERA, reference_keys=[1, 2, 3, 4])
    np.testing.assert_array_equal(second.T_qi, fresh.T_qi)
    np.testing.assert_array_equal(second.query_depth, fresh.query_depth)
    # Unkeyed references and another query image are computed anew.
    before = len(calls)
    backbone(scene["query"], scene["refs"][1:2], CAMERA)
    assert len(calls) == before + 1
    backbone(scene["refs"][0], scene["refs"][1:3], CAMERA, reference_keys=[1, 2])
    assert len(calls) == before + 3
    # A pair's result depends on its expected pose: a keyed pair with a new expectation is new.
    backbone(scene["query"], scene["refs"][1:3], CAMERA, reference_keys=[1, 2])
    assert len(calls) == before + 5
    expected = scene["T_qi"][1:3]
    for _ in range(2):
        backbone(scene["query"], scene["refs"][1:3], CAMERA, reference_keys=[1, 2], expected_T_qi=expected)
        assert len(calls) == before + 7


def test_matching_equals_the_explicit_mutual_ratio_test():
    rng = np.random.default_rng(1)
    a = np.abs(rng.standard_normal((300, 128))).astype(np.float32)
    near = a[:150] + 0.05 * np.abs(rng.standard_normal((150, 128)))
    b = np.concatenate([near, np.abs(rng.random((200, 128)))])
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = (b / np.linalg.norm(b, axis=1, keepdims=True)).astype(np.float32)
    sim = a.astype(np.float64) @ b.T.astype(np.float64)
    expected = []
    for i in range(len(a)):
        order = np.argsort(-sim[i])
        d1, d2 = np.sqrt(2 - 2 * sim[i, order[:2]])
        if d1 < 0.8 * d2 and np.argmax(sim[:, order[0]]) == i:
            expected.append((i, order[0]))
    np.testing.assert_array_equal(match_descriptors(a, b, ratio=0.8, mutual=True), np.array(expected))


def _perturbed(T_iq: np.ndarray, metres: float, degrees: float) -> np.ndarray:
    """``T_iq`` with the query moved ``metres`` sideways and turned ``degrees`` about its y axis (yaw)."""
    c, s = np.cos(np.deg2rad(degrees)), np.sin(np.deg2rad(degrees))
    turn = np.eye(4)
    turn[:3, :3] = [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]
    turn[0, 3] = metres
    return T_iq @ turn


@pytest.fixture(scope="module")
def few_matches(scene):
    """Query features cut down to 40 of its matches with reference 0 (and reference 0's features):
    RANSAC alone rejects the pair (under ``min_inliers`` = 50)."""
    backbone = ClassicalBackbone()
    fq, fr = backbone.extract(scene["query"]), backbone.extract(scene["refs"][0])
    matched = match_descriptors(fq.descriptors, fr.descriptors, 0.8, True)[:, 0]
    keep = np.random.default_rng(0).choice(matched, 40, replace=False)
    fq = type(fq)(fq.keypoints[keep], fq.descriptors[keep])
    return fq, fr, invert_pose(scene["T_qi"][0])


def test_a_prior_recovers_a_pair_ransac_rejects(few_matches):
    fq, fr, T_iq = few_matches
    backbone = ClassicalBackbone()
    pair, n, pixels = backbone.relative_pose(fq, fr, CAMERA)
    assert pair is None and len(pixels) < backbone.config.min_inliers
    # Expected 4 cm and 2 deg off: the matches near that epipolar geometry give the right pose.
    pair, n, _ = backbone.relative_pose(fq, fr, CAMERA, _perturbed(T_iq, 0.04, 2.0))
    assert pair is not None and n == pair.n_inliers >= backbone.config.guided_min_inliers
    assert np.degrees(rotation_angle(pair.R, T_iq[:3, :3])) < 0.5
    assert direction_error_deg(pair.t, T_iq[:3, 3]) < 3.0
    assert pair.confidence > 0 and len(pair.depth) > 0
    # The refinement alone (no RANSAC candidate) converges from the expected pose to the same pose.
    matches = match_descriptors(fq.descriptors, fr.descriptors, 0.8, True)
    pq, pr = fq.keypoints[matches[:, 0]], fr.keypoints[matches[:, 1]]
    R, t, inliers = backbone.guided_pose(pq, pr, CAMERA, _perturbed(T_iq, 0.04, 2.0))
    assert np.degrees(rotation_angle(R, T_iq[:3, :3])) < 0.5 and direction_error_deg(t, T_iq[:3, 3]) < 3.0
    assert inliers.sum() >= n - 3
    # Ignoring expected poses (guided_min_inliers None) leaves the pair rejected.
    off = ClassicalBackbone(ClassicalConfig(guided_min_inliers=None))
    assert off.relative_pose(fq, fr, CAMERA, _perturbed(T_iq, 0.04, 2.0))[0] is None


def _pitched(T_iq: np.ndarray, degrees: float) -> np.ndarray:
    """``T_iq`` with the query camera pitched by ``degrees`` (about its own x axis)."""
    c, s = np.cos(np.deg2rad(degrees)), np.sin(np.deg2rad(degrees))
    pitch = np.eye(4)
    pitch[1:3, 1:3] = [[c, -s], [s, c]]
    return T_iq @ pitch


def _moved_to(T: np.ndarray, t: np.ndarray) -> np.ndarray:
    moved = T.copy()
    moved[:3, 3] = t
    return moved


def test_stacked_poses_score_as_each_pose_alone(few_matches):
    """``agrees`` and ``sampson_distance`` take a stack of poses (guided_pose scores its hypotheses at
    once): each row is that pose's answer alone, and the agreement gates are the documented ones."""
    fq, fr, T_iq = few_matches
    backbone = ClassicalBackbone()
    cases = {
        "right": (T_iq, True),
        "pitched 6 deg (under guided_max_pitch_deg 9)": (_pitched(T_iq, 6.0), True),
        "pitched 12 deg": (_pitched(T_iq, 12.0), False),
        "turned 5 deg (over guided_max_rotation_deg 3)": (_perturbed(T_iq, 0.0, 5.0), False),
        "moved 0.6 m sideways": (_perturbed(T_iq, 0.6, 0.0), False),
        "no translation": (_moved_to(T_iq, np.zeros(3)), False),
    }
    assert np.linalg.norm(T_iq[:3, 3]) > backbone.config.guided_position_m  # the direction counts
    T_iqs = np.stack([T for T, _ in cases.values()])
    Rs, ts = T_iqs[:, :3, :3], T_iqs[:, :3, 3]
    agree = backbone.agrees(Rs, ts, T_iq)
    assert agree.shape == (len(cases),)
    assert agree.tolist() == [want for _, want in cases.values()], list(cases)
    for k in range(len(cases)):
        assert bool(backbone.agrees(Rs[k], ts[k], T_iq)) == agree[k]
    matches = match_descriptors(fq.descriptors, fr.descriptors, 0.8, True)
    K_inv = np.linalg.inv(CAMERA.K)
    x_q = np.c_[fq.keypoints[matches[:, 0]], np.ones(len(matches))] @ K_inv.T
    x_r = np.c_[fr.keypoints[matches[:, 1]], np.ones(len(matches))] @ K_inv.T
    stacked = sampson_distance(x_q, x_r, Rs, ts)
    assert stacked.shape == (len(cases), len(matches))
    for k in range(len(cases)):
        np.testing.assert_allclose(stacked[k], sampson_distance(x_q, x_r, Rs[k], ts[k]), rtol=1e-12)
    # The true pose explains the matches (sub-pixel), a pose 5 deg off does not.
    focal = CAMERA.K[0, 0]
    assert np.median(focal * stacked[0]) < 0.5 < np.median(focal * stacked[3])


@pytest.mark.parametrize(("metres", "degrees"), [(0.6, 15.0), (0.0, 25.0), (1.0, 0.0)])
def test_a_wrong_prior_gives_no_pair(few_matches, metres, degrees):
    fq, fr, T_iq = few_matches
    backbone = ClassicalBackbone()
    pair, _, _ = backbone.relative_pose(fq, fr, CAMERA, _perturbed(T_iq, metres, degrees))
    assert pair is None or (
        np.degrees(rotation_angle(pair.R, T_iq[:3, :3])) < 0.5
        and direction_error_deg(pair.t, T_iq[:3, 3]) < 3
    )


def test_expected_poses_leave_passing_pairs_and_are_checked(scene, result):
    _, out = result
    backbone = ClassicalBackbone()
    expected = np.stack([_perturbed(T, 0.03, 1.0) for T in scene["T_qi"]])
    guided = backbone(scene["query"], scene["refs"], CAMERA, expected_T_qi=expected)
    np.testing.assert_allclose(guided.T_qi, out.T_qi, atol=1e-6)
    np.testing.assert_array_equal(guided.n_matches, out.n_matches)
    with pytest.raises(ValueError, match="expected_T_qi"):
        backbone(scene["query"], scene["refs"], CAMERA, expected_T_qi=expected[:2])
    with pytest.raises(ValueError, match="guided_min_inliers"):
        ClassicalConfig(guided_min_inliers=3)


def test_a_pairs_dominant_plane_is_fitted_once(monkeypatch):
    """The backbone's planarity test and the verifier's off-plane matches share one homography fit
    per match set (float32 or float64 pixels alike), and a caller's edits do not reach the others."""
    import cv2

    from vgpnav_env.perception.backbones import classical

    rng = np.random.default_rng(5)
    pq = (rng.random((120, 2)) * 300).astype(np.float32)
    H = np.array([[1.0, 0.02, 4.0], [0.01, 1.0, -3.0], [0.0, 0.0, 1.0]])
    pr = cv2.perspectiveTransform(pq[None].astype(np.float64), H)[0].astype(np.float32)
    pr[:40] = rng.random((40, 2)) * 300  # a third off the plane
    fits = []
    original = cv2.findHomography
    monkeypatch.setattr(cv2, "findHomography", lambda *a, **k: fits.append(1) or original(*a, **k))
    first = classical.dominant_plane(pq.astype(np.float64), pr.astype(np.float64), 2.0)
    assert 70 <= first[40:].sum() <= 80 and first[:40].sum() <= 2 and len(fits) == 1
    first[:] = False
    again = classical.dominant_plane(pq, pr, 2.0)
    assert len(fits) == 1 and again[40:].sum() >= 70  # the same mask, untouched by the edit above
    classical.dominant_plane(pq, pr, 1.0)  # another threshold is another fit
    assert len(fits) == 2


def test_refined_matches_are_subpixel_correspondences():
    """A texture and its copy shifted by (0.4, -0.3) px: matches one pixel off (as XFeat's
    keypoints are) move to within 0.05 px of the true point; query points without texture around
    them keep their match."""
    rng = np.random.default_rng(0)
    query = cv2.GaussianBlur(rng.uniform(0, 255, (120, 160)).astype(np.float32), (0, 0), 1.5)
    query = np.clip(128 + (query - query.mean()) * 4, 0, 255).astype(np.uint8)
    shift = np.array([0.4, -0.3])
    reference = cv2.warpAffine(query, np.float32([[1, 0, shift[0]], [0, 1, shift[1]]]), (160, 120))
    grid = np.stack(np.meshgrid(np.arange(20, 140, 10), np.arange(20, 100, 10)), -1).reshape(-1, 2)
    pq = grid.astype(float)
    pr = np.round(pq + shift) + rng.choice([-1.0, 0.0, 1.0], size=pq.shape)
    refined = refine_matches(query, reference, pq, pr, 9)
    before = np.linalg.norm(pr - (pq + shift), axis=1)
    after = np.linalg.norm(refined - (pq + shift), axis=1)
    assert np.median(before) > 0.5 and np.median(after) < 0.05, (np.median(before), np.median(after))
    flat = np.full_like(query, 128)
    np.testing.assert_array_equal(refine_matches(flat, reference, pq, pr, 9), pr)
    assert refine_matches(query, reference, pq[:0], pr[:0], 9).shape == (0, 2)
    with pytest.raises(ValueError, match="refine_window"):
        ClassicalConfig(refine_window=1)
