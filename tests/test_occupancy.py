"""Point classification, log-odds fusion and egocentric crops on hand-made point sets."""

from __future__ import annotations

import numpy as np
import pytest

from vgpnav_env.grid import GridSpec
from vgpnav_env.perception.occupancy import FREE, OCCUPIED, UNKNOWN, LogOddsMap, classify_points

SPEC = GridSpec((-1.0, -1.0), 0.05, (80, 80))  # x, y in [-1, 3)
CAM_H = 1.2


def _wall_and_floor(z_ground: float = 0.0) -> np.ndarray:
    """A wall segment at x = 2.02 (y in [-0.5, 0.5], up to 1 m) and floor points for x in [0.5, 1.5]."""
    ys = np.arange(-0.5, 0.5, 0.01)
    zs = np.arange(0.2, 1.0, 0.1)
    wall = np.array([[2.02, y, z_ground + z] for y in ys for z in zs])
    fx, fy = np.meshgrid(np.arange(0.5, 1.5, 0.02), np.arange(-0.3, 0.3, 0.02))
    floor = np.stack([fx.ravel(), fy.ravel(), np.full(fx.size, z_ground + 0.01)], axis=1)
    return np.concatenate([wall, floor])


def test_classify_points_by_height() -> None:
    z = np.array([0.0, 0.04, -0.04, 0.06, 0.1, 0.15, 0.8, 1.2, 1.3, np.nan]) + 0.5
    P = np.stack([np.zeros_like(z), np.zeros_like(z), z], axis=1)
    cls = classify_points(P, z_ground=0.5, camera_height=CAM_H)
    assert cls.free.tolist() == [True, True, True, False, False, False, False, False, False, False]
    assert cls.obstacle.tolist() == [False, False, False, False, False, True, True, True, False, False]


def test_update_marks_obstacles_ground_and_ray_free_space() -> None:
    m = LogOddsMap(SPEC)
    cls = m.update(_wall_and_floor(0.3), z_ground=0.3, camera_height=CAM_H, camera_xy=(0.0, 0.0))
    assert cls.obstacle.sum() == 800 and cls.free.sum() == 1500
    wall_cells = np.unique(SPEC.world_to_cell(_wall_and_floor()[:800, :2]), axis=0)
    assert len(wall_cells) == 20 and np.allclose(
        m.logodds[wall_cells[:, 0], wall_cells[:, 1]], 0.85
    )  # once per cell, not per point
    floor_cell = SPEC.world_to_cell(np.array([1.0, 0.0]))
    assert m.logodds[tuple(floor_cell)] == pytest.approx(-0.4)
    between = SPEC.world_to_cell(np.array([1.8, 0.3]))  # not a floor point, but on a camera ray
    assert m.logodds[tuple(between)] == pytest.approx(-0.4)
    behind = SPEC.world_to_cell(np.array([2.5, 0.0]))  # behind the wall: unobserved
    side = SPEC.world_to_cell(np.array([0.5, 2.0]))
    assert m.logodds[tuple(behind)] == 0.0 and m.logodds[tuple(side)] == 0.0
    assert m.occupied().sum() == len(wall_cells)
    assert not (m.occupied() & m.free()).any()


def test_fusion_accumulates_and_clamps() -> None:
    m = LogOddsMap(SPEC, clamp=(-2.0, 2.0))
    pts = _wall_and_floor()
    for _ in range(10):
        m.update(pts, 0.0, CAM_H)
    assert m.logodds.max() == pytest.approx(2.0) and m.logodds.min() == pytest.approx(-2.0)
    # An obstacle appearing in a free cell flips it after enough observations.
    box = np.array([[1.0, 0.0, 0.5]])
    cell = tuple(SPEC.world_to_cell(box[0, :2]))
    snapshot = m.copy()
    for _ in range(5):
        m.update(box, 0.0, CAM_H)
    assert m.occupied()[cell] and snapshot.free()[cell]
    # Points outside the grid (an obstacle and a floor point) are classified but change no cell.
    before = m.logodds.copy()
    cls = m.update(np.array([[50.0, 50.0, 0.5], [-50.0, 0.0, 0.0]]), 0.0, CAM_H, camera_xy=(0.0, 0.0))
    assert cls.obstacle.tolist() == [True, False] and cls.free.tolist() == [False, True]
    np.testing.assert_array_equal(m.logodds, before)


def test_prior_and_validation() -> None:
    prior = np.zeros(SPEC.shape)
    prior[10, 10] = 10.0
    m = LogOddsMap.from_prior(SPEC, prior)
    assert m.logodds[10, 10] == 4.0 and m.probability()[0, 0] == pytest.approx(0.5)
    with pytest.raises(ValueError, match="prior shape"):
        LogOddsMap.from_prior(SPEC, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="l_free < 0 < l_occ"):
        LogOddsMap(SPEC, l_free=0.4)


@pytest.mark.parametrize("yaw", [0.0, np.pi / 2, np.pi, -2.0, 0.7])
def test_egocentric_crop_faces_up(yaw: float) -> None:
    m = LogOddsMap(SPEC)
    x, y = 1.025, 1.025  # a cell centre
    fwd = np.array([np.cos(yaw), np.sin(yaw)])
    right = np.array([np.sin(yaw), -np.cos(yaw)])
    m.logodds[tuple(SPEC.world_to_cell(np.array([x, y]) + 0.5 * fwd))] = 3.0  # 10 cells ahead
    m.logodds[tuple(SPEC.world_to_cell(np.array([x, y]) + 0.3 * right))] = 3.0  # 6 cells to the right
    m.logodds[tuple(SPEC.world_to_cell(np.array([x, y])))] = -3.0
    crop = m.egocentric_crop(x, y, yaw, size_cells=41)
    assert crop.shape == (41, 41) and crop.dtype == np.uint8
    occ = np.argwhere(crop == OCCUPIED)
    ahead = occ[occ[:, 0] < 15]
    to_right = occ[occ[:, 0] >= 15]
    # A rotated cell covers 1-2 output pixels (nearest sampling); its centre is where expected.
    assert 1 <= len(ahead) <= 2 and 1 <= len(to_right) <= 2
    assert np.abs(ahead.mean(0) - [10, 20]).max() <= 1.0
    assert np.abs(to_right.mean(0) - [20, 26]).max() <= 1.0
    assert crop[20, 20] == FREE
    assert (crop == UNKNOWN).sum() >= 41 * 41 - 6
    # Coarser output pixels halve the distances; outside the map is unknown.
    coarse = m.egocentric_crop(x, y, yaw, size_cells=31, resolution=0.1)
    assert np.abs(np.argwhere(coarse == OCCUPIED).min(0)[0] - 10) <= 1
    assert (m.egocentric_crop(50.0, 50.0, yaw, 11) == UNKNOWN).all()


@pytest.mark.parametrize("yaw", [0.0, 2.0])
def test_a_felt_contact_marks_a_segment_across_the_heading(yaw: float) -> None:
    m = LogOddsMap(SPEC)
    m.logodds[:] = -1.0  # seen free before
    pose = np.array([1.0, 1.0, yaw])
    m.mark_contact(pose, radius=0.2)
    marked = np.argwhere(m.logodds == m.clamp[1])
    xy = SPEC.cell_to_world(marked) - pose[:2]
    ahead = xy @ [np.cos(yaw), np.sin(yaw)]
    across = xy @ [-np.sin(yaw), np.cos(yaw)]
    # Half a cell (0.025 m) beyond the 0.2 m radius, +-0.1 m across; cell centres within half a
    # cell's diagonal of the segment; spanning the width (4 or more cells of 0.05 m).
    assert np.all(np.abs(ahead - 0.225) <= 0.036) and np.all(np.abs(across) <= 0.1 + 0.036)
    assert across.min() < -0.05 and across.max() > 0.05 and len(marked) >= 4
    assert (m.logodds == -1.0).sum() == m.logodds.size - len(marked)
    assert m.occupied().sum() == len(marked)
    m.mark_contact([50.0, 50.0, 0.0], radius=0.2)  # off the map: nothing changes
    assert (m.logodds == m.clamp[1]).sum() == len(marked)
    # A band as deep as a coarser crop's pixel shows in that crop, whatever its alignment.
    for x in np.linspace(1.0, 1.1, 7):
        m = LogOddsMap(SPEC)
        m.mark_contact([x, 1.0, yaw], radius=0.2, depth=0.1)
        crop = m.egocentric_crop(x, 1.0, yaw, size_cells=21, resolution=0.1)
        assert (crop[10 - 3 : 10 - 1, 9:12] == OCCUPIED).any()  # 0.2-0.3 m ahead
        assert (crop[:6] != OCCUPIED).all() and (crop[9:] != OCCUPIED).all()
