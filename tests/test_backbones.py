"""Backbone contract, registry and the privileged simulated backbone."""

from __future__ import annotations

import numpy as np
import pytest

from vgpnav_env.geometry import PinholeCamera, camera_pose, invert_pose, rotation_angle
from vgpnav_env.perception.backbones import (
    BACKBONES,
    Backbone,
    BackboneOutput,
    ClassicalBackbone,
    Privileged,
    SimulatedBackbone,
    SimulatedConfig,
    make_backbone,
)

TINY = PinholeCamera(8, 6, np.deg2rad(60.0))


def random_setup(k: int, seed: int = 0, camera: PinholeCamera = TINY):
    rng = np.random.default_rng(seed)
    T_wq = camera_pose([1.0, 2.0, 1.2], 0.3, np.deg2rad(20.0))
    T_wi = np.stack(
        [
            camera_pose(
                [*rng.uniform(0, 3, 2), 1.5], rng.uniform(-np.pi, np.pi), np.deg2rad(rng.uniform(15, 30))
            )
            for _ in range(k)
        ]
    )
    depth = rng.uniform(0.5, 5.0, (camera.height, camera.width)).astype(np.float32)
    depth[0, 0] = 0.0
    image = np.zeros((camera.height, camera.width, 3), np.uint8)
    return image, [image] * k, Privileged(T_wq, T_wi, depth), invert_pose(T_wq) @ T_wi


def rotation_angles(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Geodesic angles (radians) between stacks of rotations, via the geometry module's definition."""
    return np.array([rotation_angle(a, b) for a, b in zip(R_a, R_b, strict=True)])


def test_registry_builds_each_backbone_and_rejects_unknown_names():
    assert isinstance(make_backbone(), ClassicalBackbone)
    assert make_backbone("classical", max_keypoints=500).config.max_keypoints == 500
    sim = make_backbone("simulated", rotation_noise_deg=1.0, seed=3)
    assert isinstance(sim, SimulatedBackbone) and sim.privileged and sim.config.rotation_noise_deg == 1.0
    assert not ClassicalBackbone.privileged
    with pytest.raises(ValueError, match="unknown backbone"):
        make_backbone("vggt-online")
    with pytest.raises(TypeError):
        make_backbone("classical", no_such_knob=1)
    with pytest.raises(ValueError, match="learned backbone needs model and weights_path"):
        make_backbone("learned")
    assert sorted(BACKBONES) == ["classical", "learned", "simulated"]


def test_the_base_checks_every_backbone_input_before_reconstruct():
    class Unreachable(Backbone):
        def reconstruct(self, views):
            raise AssertionError("reconstruct runs on checked inputs only")

    image = np.zeros((TINY.height, TINY.width, 3), np.uint8)
    with pytest.raises(ValueError, match="query image must be uint8"):
        Unreachable()(image.astype(np.float32), [image], TINY)
    with pytest.raises(ValueError, match=r"reference 0 image must be uint8 with shape \(6, 8, 3\)"):
        Unreachable()(image, [image[:4]], TINY)
    with pytest.raises(ValueError, match="2 reference_keys for 1 references"):
        Unreachable()(image, [image], TINY, reference_keys=[0, 1])


def test_reseed_draws_the_episode_stream_from_the_given_generator():
    image, refs, priv, _ = random_setup(3)
    noisy = {"rotation_noise_deg": 2.0, "depth_noise": 0.05}
    a, b = make_backbone("simulated", seed=1, **noisy), make_backbone("simulated", seed=2, **noisy)
    a.reseed(np.random.default_rng(7))
    b.reseed(np.random.default_rng(7))
    out_a, out_b = a(image, refs, TINY, privileged=priv), b(image, refs, TINY, privileged=priv)
    np.testing.assert_array_equal(out_a.T_qi, out_b.T_qi)
    np.testing.assert_array_equal(out_a.query_depth, out_b.query_depth)
    b.reseed(np.random.default_rng(8))
    assert not np.array_equal(b(image, refs, TINY, privileged=priv).T_qi, out_a.T_qi)
    # A deterministic backbone draws nothing: the caller's stream is the same with or without it.
    rng = np.random.default_rng(7)
    make_backbone("classical").reseed(rng)
    assert rng.integers(2**63) == np.random.default_rng(7).integers(2**63)


def test_output_contract_validates_shapes():
    ok = dict(
        T_qi=np.tile(np.eye(4), (2, 1, 1)),
        confidence=np.array([1.0, 0.0]),
        n_matches=np.array([100, 3]),
        query_depth=np.ones((6, 8), np.float32),
        query_depth_confidence=np.ones((6, 8), np.float32),
        name="x",
        scale="test",
    )
    out = BackboneOutput(**ok)
    np.testing.assert_array_equal(out.scale_valid, [True, False])
    assert out.k == 2
    with pytest.raises(ValueError, match="confidence"):
        BackboneOutput(**{**ok, "confidence": np.ones(3)})
    with pytest.raises(ValueError, match="reference_depths"):
        BackboneOutput(**ok, reference_depths=np.ones((2, 5, 8), np.float32))


def test_simulated_without_noise_is_truth_at_one_unknown_scale():
    query, refs, priv, T_qi_true = random_setup(6)
    ref_depths = np.stack([priv.query_depth] * 6)
    priv = Privileged(priv.T_wq, priv.T_wi, priv.query_depth, ref_depths)
    backbone = SimulatedBackbone(seed=7)
    out = backbone(query, refs, TINY, privileged=priv)
    s = backbone.last_scale
    assert 0.2 <= s <= 5.0 and out.scale == "random" and out.name == "simulated"
    np.testing.assert_allclose(out.T_qi[:, :3, :3], T_qi_true[:, :3, :3], atol=1e-12)
    np.testing.assert_allclose(out.T_qi[:, :3, 3], s * T_qi_true[:, :3, 3], rtol=1e-12)
    np.testing.assert_allclose(out.query_depth, s * priv.query_depth, rtol=1e-6)
    np.testing.assert_allclose(out.reference_depths, s * ref_depths, rtol=1e-6)
    assert out.query_depth_confidence[0, 0] == 0 and out.query_depth_confidence[1:].min() == 1
    np.testing.assert_array_equal(out.confidence, 1.0)
    again = SimulatedBackbone(seed=7)(query, refs, TINY, privileged=priv)
    np.testing.assert_array_equal(again.T_qi, out.T_qi)
    scales = [backbone(query, refs, TINY, privileged=priv) and backbone.last_scale for _ in range(200)]
    assert min(scales) >= 0.2 and max(scales) <= 5.0
    # Log-uniform: the log-scale mean sits near the middle of [log 0.2, log 5] = 0.
    assert abs(np.mean(np.log(scales))) < 0.25


def test_simulated_noise_statistics_match_the_config():
    k = 3000
    query, refs, priv, T_qi_true = random_setup(k, seed=1)
    cfg = SimulatedConfig(rotation_noise_deg=2.0, direction_noise_deg=3.0, depth_noise=0.05)
    backbone = SimulatedBackbone(cfg, seed=0)
    out = backbone(query, refs, TINY, privileged=priv)
    rot = np.degrees(rotation_angles(out.T_qi[:, :3, :3], T_qi_true[:, :3, :3]))
    t_est, t_true = out.T_qi[:, :3, 3], T_qi_true[:, :3, 3]
    cos = np.einsum("ij,ij->i", t_est, t_true) / (
        np.linalg.norm(t_est, axis=1) * np.linalg.norm(t_true, axis=1)
    )
    direction = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    # RMS angles equal the configured standard deviations (half-normal angles), within 5%.
    assert np.sqrt(np.mean(rot**2)) == pytest.approx(2.0, rel=0.05)
    assert np.sqrt(np.mean(direction**2)) == pytest.approx(3.0, rel=0.05)
    # Lengths are untouched by direction noise: one common scale.
    np.testing.assert_allclose(
        np.linalg.norm(t_est, axis=1), backbone.last_scale * np.linalg.norm(t_true, axis=1)
    )
    valid = priv.query_depth > 0
    log_ratio = np.log(out.query_depth[valid] / (backbone.last_scale * priv.query_depth[valid]))
    assert abs(np.std(log_ratio) - 0.05) < 0.02


def test_simulated_outliers_are_random_with_configured_confidence():
    k = 2000
    query, refs, priv, T_qi_true = random_setup(k, seed=2)
    cfg = SimulatedConfig(outlier_fraction=0.3, outlier_confidence=(0.0, 0.2))
    out = SimulatedBackbone(cfg, seed=5)(query, refs, TINY, privileged=priv)
    rot = rotation_angles(out.T_qi[:, :3, :3], T_qi_true[:, :3, :3])
    outlier = rot > 1e-5
    # Binomial(2000, 0.3): standard deviation ~0.01 of the fraction.
    assert outlier.mean() == pytest.approx(0.3, abs=0.035)
    assert np.all(out.confidence[~outlier] == 1.0)
    assert out.confidence[outlier].max() <= 0.2
    # Uniformly random rotations have a mean angle of pi/2 + 2/pi.
    assert np.mean(rot[outlier]) == pytest.approx(np.pi / 2 + 2 / np.pi, rel=0.05)


def test_simulated_refuses_to_run_without_privileged_input():
    query, refs, priv, _ = random_setup(2)
    with pytest.raises(ValueError, match="privileged"):
        SimulatedBackbone()(query, refs, TINY)
    with pytest.raises(ValueError, match="T_wi"):
        SimulatedBackbone()(query, refs[:1], TINY, privileged=priv)
    with pytest.raises(ValueError, match="outlier_fraction"):
        SimulatedConfig(outlier_fraction=2.0)
