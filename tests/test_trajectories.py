"""Coverage trajectories on synthetic navigable grids (no renderer needed)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from vgpnav_env.geometry import camera_yaw_pitch, wrap_angle
from vgpnav_env.grid import GridSpec, largest_component
from vgpnav_env.trajectories import (
    DATABASE_HEIGHT,
    QUERY_HEIGHT,
    cover_cells,
    coverage_trajectory,
)


@pytest.fixture(scope="module")
def apartment() -> tuple[np.ndarray, GridSpec]:
    """Three rooms (~100 m2 navigable) joined by 0.5 m doors, an obstacle, and an isolated pocket."""
    spec = GridSpec((-1.0, 2.0), 0.05, (200, 240))
    nav = np.zeros(spec.shape, bool)
    nav[4:96, 4:116] = True
    nav[104:196, 4:236] = True
    nav[4:96, 124:236] = True
    nav[90:110, 50:60] = True
    nav[90:110, 180:190] = True
    nav[40:50, 110:130] = True
    nav[130:150, 100:140] = False
    pocket = np.zeros_like(nav)
    pocket[0:3, 0:3] = True
    return nav | pocket, spec


def _yaw_pitch(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    yp = np.array([camera_yaw_pitch(T) for T in poses])
    return yp[:, 0], yp[:, 1]


def test_largest_component_drops_pocket(apartment) -> None:
    nav, _ = apartment
    comp = largest_component(nav)
    assert comp.sum() == nav.sum() - 9
    assert not comp[0:3, 0:3].any()


def test_cover_cells_one_per_block_and_navigable(apartment) -> None:
    nav, spec = apartment
    comp = largest_component(nav)
    cells = cover_cells(comp, spec, 1.5)
    assert comp[cells[:, 0], cells[:, 1]].all()
    blocks = {(r // 30, c // 30) for r, c in cells}
    assert len(blocks) == len(cells)
    # Every component cell shares its 1.5 m block with a cover cell.
    rows, cols = np.nonzero(comp)
    assert {(r // 30, c // 30) for r, c in zip(rows, cols, strict=True)} == blocks


def test_database_trajectory_covers_free_space(apartment) -> None:
    nav, spec = apartment
    poses = coverage_trajectory(nav, spec, 0)
    comp = largest_component(nav)
    area = comp.sum() * spec.resolution**2
    assert 80 < area < 120
    # Modest frame budget: a few hundred frames for ~100 m2.
    assert 150 < len(poses) < 600
    xy = poses[:, :2, 3]
    dist, _ = cKDTree(xy).query(spec.centres()[comp])
    assert np.mean(dist <= 1.5) >= 0.99
    # Cameras stand on navigable cells.
    cells = spec.world_to_cell(xy)
    assert comp[cells[:, 0], cells[:, 1]].all()
    # Consecutive frames: <= spacing of travel and bounded in-place turns (30 deg + jitter).
    steps = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    assert steps.max() <= 0.3 + 1e-6
    yaw, pitch = _yaw_pitch(poses)
    turn = np.abs(wrap_angle(np.diff(yaw)))
    assert np.rad2deg(turn[steps < 1e-9]).max() <= 60 + 20 + 1e-6  # look-around step + 2 x jitter
    # Several headings are seen: all 8 compass sectors hold >= 5% of the frames.
    sectors = np.bincount(((wrap_angle(yaw) + np.pi) // (np.pi / 4)).astype(int) % 8, minlength=8)
    assert sectors.min() >= 0.05 * len(poses)


def test_heights_pitch_ranges_and_upright(apartment) -> None:
    nav, spec = apartment
    for kwargs, (h, dh) in (({}, DATABASE_HEIGHT), ({"height": QUERY_HEIGHT, "spacing": 0.5}, QUERY_HEIGHT)):
        poses = coverage_trajectory(nav, spec, 3, **kwargs)
        z = poses[:, 2, 3]
        assert z.min() >= h - dh - 1e-9 and z.max() <= h + dh + 1e-9
        assert z.max() - z.min() > dh  # spread over the range, not constant
        _, pitch = _yaw_pitch(poses)
        deg = np.rad2deg(pitch)
        assert deg.min() >= 15 - 1e-6 and deg.max() <= 30 + 1e-6
        # No roll: the camera x axis stays horizontal.
        assert np.abs(poses[:, 2, 0]).max() < 1e-9
        R = poses[:, :3, :3]
        assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-9)


def test_deterministic_per_seed(apartment) -> None:
    nav, spec = apartment
    a = coverage_trajectory(nav, spec, 7)
    b = coverage_trajectory(nav, spec, np.random.default_rng(7))
    c = coverage_trajectory(nav, spec, 8)
    assert np.array_equal(a, b)
    assert len(a) != len(c) or not np.allclose(a, c)


def test_query_trajectory_is_sparser(apartment) -> None:
    nav, spec = apartment
    db = coverage_trajectory(nav, spec, 0)
    q = coverage_trajectory(nav, spec, 1, spacing=0.5, cover_spacing=2.0, look_around_prob=0.0)
    assert len(q) < 0.7 * len(db)


def test_single_cell_and_bad_inputs() -> None:
    spec = GridSpec((0.0, 0.0), 0.1, (10, 10))
    nav = np.zeros(spec.shape, bool)
    with pytest.raises(ValueError, match="no navigable cell"):
        coverage_trajectory(nav, spec, 0)
    nav[5, 5] = True
    poses = coverage_trajectory(nav, spec, 0)
    assert len(poses) == 6  # a look-around on the spot
    assert np.allclose(poses[:, :2, 3], [0.55, 0.55])
    with pytest.raises(ValueError, match="does not match"):
        coverage_trajectory(nav[:5], spec, 0)
    with pytest.raises(ValueError, match="spacing"):
        coverage_trajectory(nav, spec, 0, spacing=0.0)
    with pytest.raises(ValueError, match="pitch"):
        coverage_trajectory(nav, spec, 0, pitch_deg=(30, 15))
