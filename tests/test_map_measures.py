"""Map measures: known answers on a hand-made map, and the measures in the registry."""

from __future__ import annotations

import numpy as np
import pytest

from vgpnav_env.geometry import PinholeCamera, yaw_pitch_rotation
from vgpnav_env.grid import GridSpec
from vgpnav_env.map_measures import (
    MapState,
    corridor,
    map_score,
    path_phantoms,
    phantom_cells,
    visible_cells,
)
from vgpnav_env.measures import MEASURES, Measurements

SPEC = GridSpec((0.0, 0.0), 0.1, (10, 10))


def hand_made() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A wall along row 5 (10 cells), all observed but the last two columns; the map has the wall's
    first six cells, one cell off by one row (col 6, row 6: within tolerance), and three phantoms
    far from it."""
    truth = np.zeros((10, 10), bool)
    truth[5, :] = True
    observed = np.ones((10, 10), bool)
    observed[:, 8:] = False
    occupied = np.zeros((10, 10), bool)
    occupied[5, :6] = True
    occupied[6, 6] = True
    occupied[1, 1] = occupied[1, 3] = occupied[2, 7] = True
    return occupied, truth, observed


def test_exact_scores_of_the_hand_made_map():
    occupied, truth, observed = hand_made()
    s = map_score(occupied, truth, observed, tolerance=0)
    # predicted observed: 6 wall + (6,6) + 3 phantoms = 10, right 6; true observed: 8, found 6
    assert (s.predicted, s.truth, s.phantoms, s.misses) == (10, 8, 4, 2)
    assert s.precision == pytest.approx(0.6)
    assert s.recall == pytest.approx(0.75)
    assert s.iou == pytest.approx(6 / (10 + 8 - 6))  # the cell IoU


def test_tolerance_forgives_one_cell_and_only_one():
    occupied, truth, observed = hand_made()
    s = map_score(occupied, truth, observed, tolerance=1)
    # (6,6) is next to the wall: right; it also finds wall cells (5,6) and (5,7); misses none
    assert (s.phantoms, s.misses) == (3, 0)
    assert s.precision == pytest.approx(0.7)
    assert s.recall == pytest.approx(1.0)
    assert s.iou == pytest.approx(1.0 / (1 / 0.7 + 1 / 1.0 - 1))
    far = np.zeros_like(occupied)
    far[7, 4] = True  # two rows off the wall
    assert map_score(far, truth, observed, tolerance=1).precision == 0.0


def test_unobserved_cells_do_not_count_and_empty_scores_are_undefined():
    occupied, truth, observed = hand_made()
    blind = np.zeros_like(observed)
    s = map_score(occupied, truth, blind)
    assert (s.precision, s.recall, s.iou, s.predicted, s.truth) == (None, None, None, 0, 0)
    only_truth = map_score(np.zeros_like(occupied), truth, observed)
    assert only_truth.precision is None and only_truth.recall == 0.0


def test_phantoms_on_the_true_path_corridor():
    occupied, truth, _ = hand_made()
    # a path along row 1 (y = 0.15 m) from x = 0 to 1 m, corridor radius 0.1 m: rows 0-2
    lane = corridor(SPEC, np.array([[0.05, 0.15], [0.95, 0.15]]), 0.1)
    assert lane[0:3].all() and not lane[3:].any()
    assert path_phantoms(occupied, truth, lane) == 3  # (1,1), (1,3), (2,7)
    assert phantom_cells(occupied, truth).sum() == 3


def test_map_measures_in_the_registry_read_one_state():
    occupied, truth, observed = hand_made()
    lane = corridor(SPEC, np.array([[0.05, 0.15], [0.95, 0.15]]), 0.1)
    m = Measurements("map")
    m.reset(MapState(occupied, truth, observed, lane))
    assert m["map_precision"].metric == pytest.approx(0.7)
    assert m["map_recall"].metric == pytest.approx(1.0)
    assert m["path_phantoms"].metric == 3
    assert {MEASURES[k].record for k in ("map_precision", "map_recall", "map_iou", "path_phantoms")} == {
        "map_precision", "map_recall", "map_iou", "path_phantom_cells"
    }  # fmt: skip


def test_visible_cells_of_a_camera_over_a_floor():
    camera = PinholeCamera(32, 24, np.radians(60.0))
    T = np.eye(4)
    T[:3, :3] = yaw_pitch_rotation(0.0, np.radians(45.0))
    T[:3, 3] = (0.0, 0.5, 1.0)
    rays = camera.rays()
    d_floor = rays @ T[:3, :3].T  # world directions with z = 1 along the optical axis
    depth = np.where(d_floor[..., 2] < 0, -1.0 / d_floor[..., 2], np.inf)  # z-depth to the floor
    seen = visible_cells(SPEC, camera, T, depth, max_height=1.3, max_depth=5.0, stride=1)
    xs = SPEC.cell_to_world(np.argwhere(seen))[:, 0]
    # 45 deg down with a 60 deg vertical fov: the floor from 1 / tan(75 deg) = 0.27 m ahead
    assert seen.any() and xs.min() > 0.2 and seen[5].any()
