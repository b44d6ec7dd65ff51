"""Grid planning: shortest paths, geodesic distances, erosion, components."""

from __future__ import annotations

import numpy as np
import pytest

from vgpnav_env.grid import (
    GridSpec,
    erode,
    geodesic_distance,
    largest_component,
    line_of_sight,
    nearest_true_cell,
    path_length,
    shortest_path,
)

SPEC = GridSpec((0.0, 0.0), 0.05, (100, 120))  # 6 m (x) by 5 m (y)


def test_bounds_and_centre_enclose_every_cell():
    spec = GridSpec((-1.0, 2.0), 0.05, (100, 120))
    lo, hi = spec.bounds
    np.testing.assert_allclose(lo, (-1.0, 2.0))
    np.testing.assert_allclose(hi, (5.0, 7.0))
    np.testing.assert_allclose(spec.centre, (2.0, 4.5))
    centres = spec.centres().reshape(-1, 2)
    assert np.all(centres > lo) and np.all(centres < hi)
    assert spec.contains(spec.world_to_cell(hi - 1e-9)) and not spec.contains(spec.world_to_cell(hi + 1e-9))


def open_grid() -> np.ndarray:
    return np.ones(SPEC.shape, bool)


def wall_grid() -> np.ndarray:
    """A wall along y = 2.5 m from x = 0 to x = 4.5 m (gap at x > 4.5 m), 2 cells thick."""
    grid = open_grid()
    grid[49:51, :90] = False
    return grid


@pytest.mark.parametrize(
    ("start", "goal"), [((0.3, 0.4), (5.6, 4.1)), ((0.5, 2.0), (5.0, 2.7)), ((1.0, 1.0), (1.2, 4.6))]
)
def test_straight_line_in_open_space(start, goal):
    path = shortest_path(open_grid(), SPEC, start, goal)
    assert path is not None
    np.testing.assert_allclose(path[0], start)
    np.testing.assert_allclose(path[-1], goal)
    euclid = float(np.linalg.norm(np.subtract(goal, start)))
    assert path_length(path) == pytest.approx(euclid, rel=0.02)
    raw = shortest_path(open_grid(), SPEC, start, goal, smooth=False)
    assert path_length(raw) >= path_length(path) - 1e-9


def test_start_and_goal_in_one_cell():
    path = shortest_path(open_grid(), SPEC, (1.01, 1.01), (1.04, 1.02))
    np.testing.assert_allclose(path, [[1.01, 1.01], [1.04, 1.02]])


def test_path_goes_around_wall_and_stays_traversable():
    grid = wall_grid()
    start, goal = (1.0, 1.0), (1.0, 4.0)
    path = shortest_path(grid, SPEC, start, goal)
    assert path is not None
    # Detour through the gap at x > 4.5 m: at least 2 * hypot(3.5, 1.5) long.
    assert path_length(path) > 2 * np.hypot(3.5, 1.5) - 0.05
    for a, b in zip(path[:-1], path[1:], strict=True):
        assert line_of_sight(grid, SPEC, a, b)


def test_geodesic_distance_around_wall():
    grid = wall_grid()
    goal = (1.0, 4.0)
    dist = geodesic_distance(grid, SPEC, goal)
    assert dist.shape == SPEC.shape
    assert dist[SPEC.world_to_cell(np.array(goal))[0], SPEC.world_to_cell(np.array(goal))[1]] == 0.0
    r, c = SPEC.world_to_cell(np.array([1.0, 1.0]))
    assert dist[r, c] > 2 * np.hypot(3.5, 1.5) - 0.05 > 3.0  # Euclidean is 3 m
    assert np.all(np.isinf(dist[~grid]))
    # Open space: octile distance is within 8.3% above Euclidean.
    d_open = geodesic_distance(open_grid(), SPEC, goal)
    r, c = SPEC.world_to_cell(np.array([5.0, 0.5]))
    euclid = np.hypot(4.0, 3.5)
    assert euclid - 0.1 <= d_open[r, c] <= 1.083 * euclid + 0.1


def test_unreachable():
    grid = wall_grid()
    grid[49:51, :] = False  # close the gap
    assert shortest_path(grid, SPEC, (1.0, 1.0), (1.0, 4.0)) is None
    dist = geodesic_distance(grid, SPEC, (1.0, 4.0))
    r, c = SPEC.world_to_cell(np.array([1.0, 1.0]))
    assert np.isinf(dist[r, c])
    # Start or goal on a blocked cell.
    assert shortest_path(grid, SPEC, (1.0, 2.5), (1.0, 4.0)) is None
    assert np.all(np.isinf(geodesic_distance(grid, SPEC, (1.0, 2.5))))


def test_off_grid_and_shape_errors():
    with pytest.raises(ValueError, match="start .* off the grid"):
        shortest_path(open_grid(), SPEC, (-1.0, 1.0), (1.0, 1.0))
    with pytest.raises(ValueError, match="goal .* off the grid"):
        geodesic_distance(open_grid(), SPEC, (1.0, 9.0))
    with pytest.raises(ValueError, match="shape"):
        shortest_path(np.ones((3, 3), bool), SPEC, (1.0, 1.0), (2.0, 2.0))
    with pytest.raises(ValueError, match="radius_m"):
        erode(open_grid(), -0.1, SPEC)


def test_erode_matches_disc_clearance():
    grid = open_grid()
    eroded = erode(grid, 0.22, SPEC)  # grid border counts as an obstacle
    # Cells whose centre is >= 0.22 m from the nearest outside-cell centre (-0.025 / 6.025 m).
    centres = SPEC.centres()
    x, y = centres[..., 0], centres[..., 1]
    expected = (x + 0.025 >= 0.22) & (6.025 - x >= 0.22) & (y + 0.025 >= 0.22) & (5.025 - y >= 0.22)
    np.testing.assert_array_equal(eroded, expected)
    assert erode(grid, 0.0, SPEC).all()


def test_nearest_and_largest_component():
    grid = open_grid()
    grid[39:41, :] = False  # south part 39 rows, north part 59 rows
    big = largest_component(grid)
    assert big.sum() == 59 * 120 and big[60, 10] and not big[10, 10]
    assert nearest_true_cell(grid, (39, 7)) == (38, 7)
    assert nearest_true_cell(np.zeros((3, 3), bool), (1, 1)) is None
    assert not largest_component(np.zeros((3, 3), bool)).any()
