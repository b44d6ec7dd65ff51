"""Weighted motion averaging on synthetic reference sets with known query pose."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vgpnav_env.geometry import camera_pose, invert_pose, make_pose, rotation_angle
from vgpnav_env.perception.motion_averaging import (
    MotionAveragingConfig,
    average_motion,
    metric_centre,
    triangulate_rays,
)

UNKNOWN_SCALE = 0.37


def _small_rotation(rng: np.random.Generator, deg: float) -> Rotation:
    """Random rotation with rms angle ``deg`` (isotropic Gaussian rotation vector)."""
    return Rotation.from_rotvec(rng.normal(0.0, np.deg2rad(deg) / np.sqrt(3.0), 3))


def _scenario(
    rng: np.random.Generator,
    k: int = 10,
    rot_noise_deg: float = 0.5,
    dir_noise_deg: float = 0.5,
    n_dir_outliers: int = 0,
    n_rot_outliers: int = 0,
    distance: float = 3.0,
):
    """References around a query at ~``distance`` m; backbone poses with noise and outliers."""
    T_wq = camera_pose([1.0, 2.0, 1.2], yaw=0.3, pitch=np.deg2rad(20))
    T_wi = []
    for _ in range(k):
        az = rng.uniform(-np.pi, np.pi)
        offset = distance * np.array([np.cos(az), np.sin(az), 0.0]) + [0, 0, rng.uniform(-0.5, 0.5)]
        T_wi.append(camera_pose(T_wq[:3, 3] + offset, yaw=rng.uniform(-np.pi, np.pi), pitch=0.3))
    T_wi = np.array(T_wi)
    T_qi = []
    for i in range(k):
        T_iq = invert_pose(T_wi[i]) @ T_wq
        R_iq = Rotation.from_matrix(T_iq[:3, :3])
        R_iq = R_iq * _small_rotation(rng, rot_noise_deg)
        t_iq = _small_rotation(rng, dir_noise_deg).apply(T_iq[:3, 3])
        if i < n_dir_outliers:
            t_iq = Rotation.from_rotvec(rng.normal(size=3) * 0.8).apply(t_iq)
        if n_dir_outliers <= i < n_dir_outliers + n_rot_outliers:
            R_iq = Rotation.random(random_state=rng.integers(1 << 30)) * R_iq
        T_qi.append(invert_pose(make_pose(R_iq, UNKNOWN_SCALE * t_iq)))
    conf = rng.uniform(0.6, 1.0, k)
    return T_wq, T_wi, np.array(T_qi), conf


@pytest.mark.parametrize("seed", range(5))
def test_translation_with_noise_and_gross_outliers(seed: int) -> None:
    rng = np.random.default_rng(seed)
    T_wq, T_wi, T_qi, conf = _scenario(rng, k=10, n_dir_outliers=2)
    res = average_motion(T_wi, T_qi, conf)
    assert res.ok, res.reason
    err = np.linalg.norm(res.T_wq[:3, 3] - T_wq[:3, 3])
    assert err < 0.02, f"position error {err:.4f} m"
    assert rotation_angle(res.T_wq[:3, :3], T_wq[:3, :3]) < np.deg2rad(0.5)
    # The two gross outliers are flagged; the triangulation implies the backbone's scale.
    assert not res.inliers[:2].any() and res.inliers[2:].sum() >= 7
    assert res.scale_from_rays == pytest.approx(1.0 / UNKNOWN_SCALE, rel=0.02)


def test_weighted_beats_unweighted_translation() -> None:
    errs_w, errs_ls = [], []
    for seed in range(10):
        rng = np.random.default_rng(100 + seed)
        T_wq, T_wi, T_qi, conf = _scenario(rng, k=10, n_dir_outliers=2)
        res = average_motion(T_wi, T_qi, conf)
        errs_w.append(np.linalg.norm(res.T_wq[:3, 3] - T_wq[:3, 3]))
        T_iq = invert_pose(T_qi)
        v = np.einsum("kij,kj->ki", T_wi[:, :3, :3], T_iq[:, :3, 3])
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        p, _ = triangulate_rays(T_wi[:, :3, 3], v, np.ones(10))
        errs_ls.append(np.linalg.norm(p - T_wq[:3, 3]))
    assert np.median(errs_w) < 0.015
    assert np.median(errs_ls) > 5 * np.median(errs_w)


def test_rotation_averaging_with_outliers_beats_plain_mean() -> None:
    errs_w, errs_mean = [], []
    for seed in range(10):
        rng = np.random.default_rng(200 + seed)
        T_wq, T_wi, T_qi, conf = _scenario(rng, k=20, rot_noise_deg=1.0, n_rot_outliers=6)
        # Outliers are confident, inliers less so: the consensus must come from support, not confidence.
        conf[:6] = 1.0
        conf[6:] = 0.5
        res = average_motion(T_wi, T_qi, conf)
        assert res.ok, res.reason
        assert res.consensus >= 13 and not res.inliers[:6].any()
        errs_w.append(np.rad2deg(rotation_angle(res.T_wq[:3, :3], T_wq[:3, :3])))
        hyp = np.einsum("kij,kjl->kil", T_wi[:, :3, :3], invert_pose(T_qi)[:, :3, :3])
        errs_mean.append(
            np.rad2deg(rotation_angle(Rotation.from_matrix(hyp).mean().as_matrix(), T_wq[:3, :3]))
        )
    assert max(errs_w) < 0.5, errs_w
    assert np.median(errs_mean) > 5 * np.median(errs_w)


def test_ray_behind_the_reference_is_rejected() -> None:
    rng = np.random.default_rng(7)
    T_wq, T_wi, T_qi, conf = _scenario(rng, k=6, rot_noise_deg=0.2, dir_noise_deg=0.2)
    T_iq = invert_pose(T_qi[0])
    T_iq[:3, 3] *= -1.0  # the query centre is claimed to be behind reference 0
    T_qi[0] = invert_pose(T_iq)
    res = average_motion(T_wi, T_qi, conf)
    assert res.ok and not res.inliers[0] and res.weights[0] == 0.0
    assert np.linalg.norm(res.T_wq[:3, 3] - T_wq[:3, 3]) < 0.02


def test_failures_are_reported_not_raised() -> None:
    rng = np.random.default_rng(3)
    T_wq, T_wi, T_qi, conf = _scenario(rng, k=6)
    one = average_motion(T_wi[:1], T_qi[:1], conf[:1])
    assert not one.ok and one.reason == "no consensus"
    assert (
        average_motion(np.zeros((0, 4, 4)), np.zeros((0, 4, 4)), np.zeros(0)).reason == "too few references"
    )
    # Every rotation disagrees with every other one.
    _, T_wi_r, T_qi_r, conf_r = _scenario(rng, k=6, n_rot_outliers=6)
    assert average_motion(T_wi_r, T_qi_r, conf_r).reason == "no consensus"
    # All references on one line through the query: parallel rays cannot fix the depth.
    T_wi_line = np.array([camera_pose(T_wq[:3, 3] + [d, 0, 0], yaw=0.0, pitch=0.0) for d in (1.0, 2.0, 3.0)])
    T_qi_line = np.array([invert_pose(T_wq) @ T for T in T_wi_line])
    res = average_motion(T_wi_line, T_qi_line, np.ones(3))
    assert not res.ok and res.reason == "degenerate rays"
    with pytest.raises(ValueError, match="need T_wi"):
        average_motion(T_wi, T_qi[:3], conf)


def test_single_reference_ablation_needs_the_scale() -> None:
    rng = np.random.default_rng(11)
    T_wq, T_wi, T_qi, conf = _scenario(rng, k=5, rot_noise_deg=0.0, dir_noise_deg=0.0)
    cfg = MotionAveragingConfig(method="single")
    exact = average_motion(T_wi, T_qi, conf, cfg, single_scale=1.0 / UNKNOWN_SCALE)
    assert exact.ok and exact.inliers.sum() == 1 and exact.inliers[0]
    np.testing.assert_allclose(exact.T_wq, T_wq, atol=1e-9)
    unscaled = average_motion(T_wi, T_qi, conf, cfg)
    assert np.linalg.norm(unscaled.T_wq[:3, 3] - T_wq[:3, 3]) > 1.0
    by_conf = average_motion(
        T_wi, T_qi, conf, MotionAveragingConfig(method="single", single_reference="confidence")
    )
    assert by_conf.inliers[np.argmax(conf)]


def test_failed_pairs_and_unscaled_pairs() -> None:
    rng = np.random.default_rng(21)
    T_wq, T_wi, T_qi, conf = _scenario(rng, k=8, rot_noise_deg=0.2, dir_noise_deg=0.2)
    # Pairs 0-2 failed in the backbone (confidence 0, identity pose): ignored entirely.
    T_qi[:3] = np.eye(4)
    conf[:3] = 0.0
    # Pair 3 has a usable direction but a length on another scale.
    T_iq = invert_pose(T_qi[3])
    T_iq[:3, 3] *= 5.0
    T_qi[3] = invert_pose(T_iq)
    valid = np.ones(8, bool)
    valid[3] = False
    res = average_motion(T_wi, T_qi, conf, scale_valid=valid)
    assert res.ok and not res.inliers[:3].any() and res.inliers[3:].all()
    assert np.linalg.norm(res.T_wq[:3, 3] - T_wq[:3, 3]) < 0.02
    assert res.scale_from_rays == pytest.approx(1.0 / UNKNOWN_SCALE, rel=0.01)


def test_consensus_prefers_confident_agreement_over_a_weak_repeated_cluster() -> None:
    """Five weak pairs agreeing on a rotation 90 deg off (a repeated wall texture) lose to four
    confident correct pairs; with equal confidences the larger cluster would win."""
    rng = np.random.default_rng(3)
    T_wq, T_wi, T_qi, _ = _scenario(rng, k=9, rot_noise_deg=0.2, dir_noise_deg=0.2)
    turn = make_pose(Rotation.from_euler("y", 90, degrees=True).as_matrix(), np.zeros(3))
    T_qi[4:] = turn @ T_qi[4:]  # the query turned by 90 deg about its vertical axis, same for all 5
    conf = np.r_[np.full(4, 0.2), np.full(5, 0.11)]
    res = average_motion(T_wi, T_qi, conf)
    assert res.ok and res.consensus == 4
    assert np.degrees(rotation_angle(res.T_wq[:3, :3], T_wq[:3, :3])) < 0.5
    equal = average_motion(T_wi, T_qi, np.full(9, 0.2))
    assert equal.consensus == 5


def _corridor(rng: np.random.Generator, dir_noise_deg: float = 3.0, scale_error: float = 0.0):
    """A query ahead of three references in a corridor (rays 10-25 deg apart): the rays fix the
    centre across the corridor, poorly along it. Returns the truth, the references, the backbone's
    relative poses (unit scale ``UNKNOWN_SCALE``) and the metric scale, off by ``scale_error``."""
    T_wq = camera_pose([3.0, 0.0, 1.2], yaw=0.0, pitch=np.deg2rad(20))
    T_wi = np.array(
        [camera_pose([3.0 - back, side, 1.2], yaw=0.0, pitch=np.deg2rad(20)) for back, side in
         [(0.8, 0.3), (1.3, -0.3), (1.8, 0.2)]]
    )  # fmt: skip
    T_qi = []
    for T in T_wi:
        T_iq = invert_pose(T) @ T_wq
        t_iq = _small_rotation(rng, dir_noise_deg).apply(T_iq[:3, 3])
        T_qi.append(invert_pose(make_pose(T_iq[:3, :3], UNKNOWN_SCALE * t_iq)))
    return T_wq, T_wi, np.array(T_qi), (1.0 + scale_error) / UNKNOWN_SCALE


def test_metric_distances_place_the_centre_along_nearly_parallel_rays() -> None:
    rays, metric = [], []
    for seed in range(30):
        T_wq, T_wi, T_qi, scale = _corridor(np.random.default_rng(seed), scale_error=0.02)
        res = average_motion(T_wi, T_qi, np.ones(3))
        assert res.ok, res.reason
        T = metric_centre(res, T_wi, invert_pose(T_qi), scale, np.ones(3, bool))
        np.testing.assert_allclose(T[:3, :3], res.T_wq[:3, :3])  # the rotation is kept
        rays.append(np.linalg.norm(res.T_wq[:3, 3] - T_wq[:3, 3]))
        metric.append(np.linalg.norm(T[:3, 3] - T_wq[:3, 3]))
    # Rays 3 deg off leave the centre 5 cm or more off along the corridor in most draws (0.4 within:
    # 12 of 30); with distances 2 % off, 0.7 of them are within 5 cm (21 of 30).
    rays, metric = np.array(rays), np.array(metric)
    assert (rays < 0.05).mean() <= 0.5 and (metric < 0.05).mean() >= 0.6
    assert np.median(metric) < 0.75 * np.median(rays)


def test_metric_centre_without_distances_keeps_the_rays_pose() -> None:
    T_wq, T_wi, T_qi, scale = _corridor(np.random.default_rng(0))
    res = average_motion(T_wi, T_qi, np.ones(3))
    T_iq = invert_pose(T_qi)
    off = MotionAveragingConfig(distance_sigma=None)
    np.testing.assert_array_equal(metric_centre(res, T_wi, T_iq, scale, np.ones(3, bool), off), res.T_wq)
    np.testing.assert_array_equal(metric_centre(res, T_wi, T_iq, float("nan"), np.ones(3, bool)), res.T_wq)
    np.testing.assert_array_equal(metric_centre(res, T_wi, T_iq, scale, np.zeros(3, bool)), res.T_wq)
    # Exact rays and distances: the same centre either way.
    T_wq, T_wi, T_qi, scale = _corridor(np.random.default_rng(0), dir_noise_deg=0.0)
    res = average_motion(T_wi, T_qi, np.ones(3))
    T = metric_centre(res, T_wi, invert_pose(T_qi), scale, np.ones(3, bool))
    np.testing.assert_allclose(T[:3, 3], T_wq[:3, 3], atol=1e-6)
    with pytest.raises(ValueError, match="distance_sigma"):
        MotionAveragingConfig(distance_sigma=0.0)
