"""Ground-anchored scale recovery on analytically ray-cast boxes-in-a-room scenes."""

from __future__ import annotations

import numpy as np
import pytest

from vgpnav_env.geometry import PinholeCamera, camera_pose, invert_pose, transform_points
from vgpnav_env.perception.scale_recovery import (
    GroundAnchor,
    GroundEstimate,
    ScaleConfig,
    ground_peak,
    reconstruction_points,
    recover_metric_points,
)

CAM = PinholeCamera(160, 120, np.deg2rad(60))
ROOM = (np.array([-3.0, -3.0, 0.0]), np.array([5.0, 3.0, 2.5]))
BOXES = [  # table, low crate, cabinet against a wall
    (np.array([1.2, -0.6, 0.0]), np.array([2.2, 0.4, 0.75])),
    (np.array([1.5, 0.8, 0.0]), np.array([2.3, 1.6, 0.4])),
    (np.array([3.5, -2.0, 0.0]), np.array([4.5, -1.0, 1.8])),
]
UNKNOWN_SCALE = 0.37  # backbone units per metre
CAMERA_HEIGHT = 1.2


def _slabs(origin, dirs, lo, hi):
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - origin) / dirs
        t2 = (hi - origin) / dirs
    return np.nanmax(np.minimum(t1, t2), axis=1), np.nanmin(np.maximum(t1, t2), axis=1)


def raycast_depth(T_wc: np.ndarray, boxes=BOXES) -> np.ndarray:
    """Metric z-depth (H, W) of the room interior and solid boxes seen from ``T_wc``."""
    rays_c = CAM.rays().reshape(-1, 3)  # z = 1, so the ray parameter is the z-depth
    dirs = rays_c @ T_wc[:3, :3].T
    o = T_wc[:3, 3]
    _, t = _slabs(o, dirs, *ROOM)  # leaving the room from inside
    for lo, hi in boxes:
        t_in, t_out = _slabs(o, dirs, lo, hi)
        hit = (t_in < t_out) & (t_in > 0)
        t = np.where(hit, np.minimum(t, t_in), t)
    return t.reshape(CAM.height, CAM.width)


def backbone_points(
    T_wc: np.ndarray, rng: np.random.Generator, noise: float = 0.01, boxes=BOXES
) -> np.ndarray:
    """Query-frame points (H, W, 3) at the backbone's unknown scale with relative depth noise."""
    depth = raycast_depth(T_wc, boxes) * UNKNOWN_SCALE
    return CAM.backproject(depth * (1.0 + rng.normal(0.0, noise, depth.shape)))


@pytest.mark.parametrize("pitch_deg,yaw", [(20.0, 0.0), (10.0, 0.4), (30.0, -0.5), (20.0, 2.5)])
def test_scale_within_one_percent(pitch_deg: float, yaw: float) -> None:
    rng = np.random.default_rng(0)
    T_wc = camera_pose([0.0, 0.0, CAMERA_HEIGHT], yaw, np.deg2rad(pitch_deg))
    g = ground_peak(backbone_points(T_wc, rng), T_wc[:3, :3])
    assert g.found and g.support > 0.1
    assert g.height_b == pytest.approx(-CAMERA_HEIGHT * UNKNOWN_SCALE, rel=0.01)

    anchor = GroundAnchor()
    anchor.initialize([(T_wc, g)], camera_height_m=CAMERA_HEIGHT)
    assert anchor.z_ground == pytest.approx(0.0, abs=1e-9)
    assert anchor.initial_scales == pytest.approx([1.0 / UNKNOWN_SCALE], rel=0.01)
    # A later frame elsewhere with a fresh backbone output (same unknown scale here).
    T_next = camera_pose([0.5, 0.8, CAMERA_HEIGHT], yaw + 0.3, np.deg2rad(pitch_deg))
    est = anchor.scale_for(T_next, ground_peak(backbone_points(T_next, rng), T_next[:3, :3]))
    assert est.source == "ground" and est.scale == pytest.approx(1.0 / UNKNOWN_SCALE, rel=0.01)


def test_noisy_depth_still_finds_the_floor() -> None:
    """5 % per-pixel depth noise smears the floor peak; the scale stays within 2 %."""
    errors = []
    for seed in range(10):
        rng = np.random.default_rng(seed)
        T_wc = camera_pose(
            [rng.uniform(-1, 0.5), rng.uniform(-1, 1), CAMERA_HEIGHT],
            rng.uniform(-1, 1),
            np.deg2rad(rng.uniform(10, 30)),
        )
        g = ground_peak(backbone_points(T_wc, rng, noise=0.05), T_wc[:3, :3])
        assert g.found
        errors.append(g.height_b / (-CAMERA_HEIGHT * UNKNOWN_SCALE) - 1.0)
    assert np.max(np.abs(errors)) < 0.02, errors


def _table_scene():
    """A camera 45 deg down over a floor with a 0.75 m table top (backbone units): T_wc, points."""
    rng = np.random.default_rng(1)
    table = [(np.array([0.6, -1.5, 0.0]), np.array([2.0, 1.5, 0.75]))]
    T_wc = camera_pose([0.0, 0.0, CAMERA_HEIGHT], 0.0, np.deg2rad(45))
    return T_wc, backbone_points(T_wc, rng, boxes=table)


def test_table_top_does_not_replace_the_floor() -> None:
    """A table top with twice the floor's points peaks higher; the floor below still wins."""
    T_wc, pts = _table_scene()
    g = ground_peak(pts, T_wc[:3, :3])
    assert g.found and g.height_b == pytest.approx(-CAMERA_HEIGHT * UNKNOWN_SCALE, rel=0.01)
    # Strictly the dominant peak (relative_peak_support=1) is the table top, 0.45 m below the camera.
    top = ground_peak(pts, T_wc[:3, :3], config=ScaleConfig(relative_peak_support=1.0))
    assert top.support > g.support and top.height_b == pytest.approx(-0.45 * UNKNOWN_SCALE, rel=0.01)


def test_points_under_a_table_top_tell_it_from_the_floor() -> None:
    """Nothing lies under the floor; a table top taken for the ground has the floor under it."""
    T_wc, pts = _table_scene()
    floor = ground_peak(pts, T_wc[:3, :3])
    top = ground_peak(pts, T_wc[:3, :3], config=ScaleConfig(relative_peak_support=1.0))
    h = pts.reshape(-1, 3) @ T_wc[2, :3]  # heights (backbone units) in the gravity frame
    expected = np.mean(h < top.height_b * 1.125)  # more than 12.5 % of its depth under the top
    assert floor.below < 0.001 and expected > 0.1
    assert top.below == pytest.approx(expected, abs=0.01)
    assert not ground_peak(np.zeros((0, 3)), np.eye(3)).below
    with pytest.raises(ValueError, match="below_margin"):
        ScaleConfig(below_margin=-0.1)


def test_no_ground_visible() -> None:
    rng = np.random.default_rng(2)
    # Looking up: nothing below the camera except wall.
    T_up = camera_pose([0.0, 0.0, CAMERA_HEIGHT], 0.0, np.deg2rad(-35))
    assert not ground_peak(backbone_points(T_up, rng), T_up[:3, :3]).found
    # Level camera 0.4 m in front of a wall: the wall fills the view, the floor is out of frame.
    T_wall = camera_pose([4.6, 0.0, CAMERA_HEIGHT], 0.0, 0.0)
    pts = backbone_points(T_wall, rng)
    assert (pts.reshape(-1, 3) @ T_wall[2, :3] < 0).mean() > 0.4
    assert not ground_peak(pts, T_wall[:3, :3]).found
    # Too few points at all.
    assert not ground_peak(np.zeros((0, 3)), np.eye(3)).found


def test_weights_and_scale_equivariance() -> None:
    rng = np.random.default_rng(3)
    T_wc = camera_pose([0.0, 0.0, CAMERA_HEIGHT], 0.2, np.deg2rad(20))
    pts = backbone_points(T_wc, rng)
    g1 = ground_peak(pts, T_wc[:3, :3])
    g2 = ground_peak(pts * 7.0, T_wc[:3, :3])
    assert g2.height_b == pytest.approx(7.0 * g1.height_b, rel=1e-6)
    # Zero-weight (e.g. unconfident) pixels are ignored: with the floor hidden, the crate top (0.4 m)
    # is the lowest peak.
    w = np.ones(pts.shape[:2])
    w[(pts @ T_wc[2, :3]) < -0.9 * CAMERA_HEIGHT * UNKNOWN_SCALE] = 0.0
    g3 = ground_peak(pts, T_wc[:3, :3], w)
    assert g3.found and g3.height_b == pytest.approx(-0.8 * UNKNOWN_SCALE, rel=0.02)
    with pytest.raises(ValueError, match="weights have"):
        ground_peak(pts, T_wc[:3, :3], np.ones(3))


def test_anchor_fallback_disabled_and_metric_points() -> None:
    rng = np.random.default_rng(4)
    T_wc = camera_pose([1.0, 0.5, CAMERA_HEIGHT + 0.01], 0.0, np.deg2rad(20))
    anchor = GroundAnchor()
    with pytest.raises(RuntimeError, match="initialize"):
        anchor.scale_for(T_wc, GroundEstimate(-1.0, 1.0, True))
    anchor.initialize([(camera_pose([0, 0, z], 0.0, 0.3), None) for z in (1.19, 1.21)], CAMERA_HEIGHT)
    assert anchor.z_ground == pytest.approx(0.0)
    lost = GroundEstimate(float("nan"), 0.0, False)
    assert anchor.scale_for(T_wc, lost, fallback_scale=2.5).source == "fallback"
    assert not anchor.scale_for(T_wc, lost).ok
    off = GroundAnchor(ScaleConfig(enabled=False))
    off.initialize([(T_wc, None)], CAMERA_HEIGHT)
    assert off.scale_for(T_wc, GroundEstimate(-0.1, 1.0, True)).scale == 1.0
    # Metric points from the recovered scale match the true geometry.
    pts = backbone_points(T_wc, rng, noise=0.0)
    g = ground_peak(pts, T_wc[:3, :3])
    est = anchor.scale_for(T_wc, g)
    P_w = recover_metric_points(pts, T_wc, est.scale)
    truth = transform_points(T_wc, CAM.backproject(raycast_depth(T_wc)))
    np.testing.assert_allclose(P_w, truth, atol=0.01 * 8.0)
    floor = truth[..., 2] < 0.01
    assert np.abs(P_w[floor][:, 2]).max() < 0.01


def test_references_supply_the_ground_the_query_cannot_see() -> None:
    T_wq = camera_pose([4.6, 0.0, CAMERA_HEIGHT], 0.0, 0.0)  # facing a wall, no floor in view
    T_wi = np.array([camera_pose([1.0, y, 1.5], 0.0, np.deg2rad(25)) for y in (-1.0, 1.0)])
    T_qi = np.array([invert_pose(T_wq) @ T for T in T_wi])
    T_qi[:, :3, 3] *= UNKNOWN_SCALE
    q_depth = raycast_depth(T_wq) * UNKNOWN_SCALE
    r_depth = np.array([raycast_depth(T) for T in T_wi]) * UNKNOWN_SCALE
    P, w = reconstruction_points(CAM, q_depth)
    assert not ground_peak(P, T_wq[:3, :3], w).found
    P, w = reconstruction_points(CAM, q_depth, None, T_qi, r_depth, np.array([0.9, 0.8]))
    g = ground_peak(P, T_wq[:3, :3], w)
    assert g.found and g.height_b == pytest.approx(-CAMERA_HEIGHT * UNKNOWN_SCALE, rel=0.01)
    # Zero-weight references (failed pairs) add nothing.
    P0, _ = reconstruction_points(CAM, q_depth, None, T_qi, r_depth, np.zeros(2))
    assert len(P0) == len(reconstruction_points(CAM, q_depth)[0])
    with pytest.raises(ValueError, match="reference_depths"):
        reconstruction_points(CAM, q_depth, None, T_qi[:1], r_depth)


def test_prior_from_a_scale_hint_picks_the_matching_peak() -> None:
    rng = np.random.default_rng(6)
    table = [(np.array([0.6, -1.5, 0.0]), np.array([2.0, 1.5, 0.75]))]
    T_wc = camera_pose([0.0, 0.0, CAMERA_HEIGHT], 0.0, np.deg2rad(45))
    pts = backbone_points(T_wc, rng, boxes=table)
    strict = ScaleConfig(relative_peak_support=1.0)  # would take the table top without a prior
    anchor = GroundAnchor(strict)
    anchor.initialize([(T_wc, None)], CAMERA_HEIGHT)
    prior = anchor.expected_height_b(T_wc, scale_hint=1.1 / UNKNOWN_SCALE)  # a 10 % off scale guess
    g = ground_peak(pts, T_wc[:3, :3], config=strict, prior_height_b=prior)
    assert g.found and g.height_b == pytest.approx(-CAMERA_HEIGHT * UNKNOWN_SCALE, rel=0.01)
    assert anchor.scale_for(T_wc, g).scale == pytest.approx(1.0 / UNKNOWN_SCALE, rel=0.01)
    # A prior matching nothing: no ground rather than a wrong one.
    assert not ground_peak(pts, T_wc[:3, :3], prior_height_b=prior * 0.2).found
    assert anchor.expected_height_b(T_wc, float("nan")) is None
