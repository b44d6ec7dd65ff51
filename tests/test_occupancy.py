"""Point classification, log-odds fusion and egocentric crops on hand-made point sets."""

from __future__ import annotations

import numpy as np
import pytest

from vgpnav_env.grid import GridSpec
from vgpnav_env.perception.occupancy import (
    FREE,
    OCCUPIED,
    UNKNOWN,
    LogOddsMap,
    OccupancyConfig,
    classify_points,
)

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


def _fuse(m: LogOddsMap, points, camera_xy, config: OccupancyConfig | None = None) -> None:
    """One frame through the perceiver's fusion options (camera 1.2 m above the ground at z = 0)."""
    config = config or OccupancyConfig()
    m.update(
        np.asarray(points, float), 0.0, 1.2, camera_xy=camera_xy,
        clear_height=config.clear_height, min_cell_points=config.min_cell_points,
        max_obstacle_range=config.max_obstacle_range, protect_free=config.protect_free,
    )  # fmt: skip


def _cell_points(xy, z, n: int = 4) -> np.ndarray:
    """``n`` points at height ``z`` spread inside the 0.05 m cell whose centre is ``xy``."""
    offsets = np.linspace(-0.015, 0.015, n)
    return np.array([[xy[0] + o, xy[1] - o, z] for o in offsets])


def _floor(x0: float, x1: float, y: float) -> np.ndarray:
    xs = np.arange(x0, x1, 0.01)
    return np.stack([xs, np.full_like(xs, y), np.zeros_like(xs)], axis=1)


def test_a_phantom_seen_free_from_two_later_frames_is_cleared() -> None:
    m = LogOddsMap(SPEC)
    phantom = (1.525, 1.025)  # a cell centre
    cell = tuple(SPEC.world_to_cell(np.array(phantom)))
    _fuse(m, _cell_points(phantom, 0.3), camera_xy=(0.3, 1.0))  # noisy depth: an obstacle point cluster
    assert m.occupied()[cell]
    for camera_x in (0.2, 0.5):  # two later frames see the floor there and beyond it
        _fuse(m, _floor(1.3, 2.2, 1.025), camera_xy=(camera_x, 1.0))
    assert not m.occupied()[cell] and m.logodds[cell] < 0.62


@pytest.mark.parametrize("l_occ", [0.85, 2.0, 4.0])
def test_a_doorway_seen_open_is_not_closed_by_one_frame(l_occ: float) -> None:
    config = OccupancyConfig(l_occ=l_occ)
    m = LogOddsMap(SPEC, l_occ=l_occ)
    door = [(1.525, y) for y in (0.925, 0.975, 1.025, 1.075)]  # a 0.2 m doorway across y
    _fuse(m, np.concatenate([_floor(1.4, 1.7, y) for _, y in door]), (0.5, 1.0), config)  # seen open
    cells = SPEC.world_to_cell(np.array(door))
    assert (m.logodds[cells[:, 0], cells[:, 1]] < 0).all()
    # one frame's points fill the doorway (e.g. a wrong depth): it stays open
    _fuse(m, np.concatenate([_cell_points(d, 0.8) for d in door]), (0.5, 1.0), config)
    assert not m.occupied()[cells[:, 0], cells[:, 1]].any()
    # the old fusion (no protection) closes it when one frame's evidence outweighs the free one
    if l_occ > 0.4 + 0.62:
        plain = LogOddsMap(SPEC, l_occ=l_occ)
        plain.update(np.concatenate([_floor(1.4, 1.7, y) for _, y in door]), 0.0, 1.2, camera_xy=(0.5, 1.0))
        plain.update(np.concatenate([_cell_points(d, 0.8) for d in door]), 0.0, 1.2, camera_xy=(0.5, 1.0))
        assert plain.occupied()[cells[:, 0], cells[:, 1]].all()
    # a second frame does close it (a door that was closed meanwhile)
    _fuse(m, np.concatenate([_cell_points(d, 0.8) for d in door]), (0.5, 1.0), config)
    assert m.occupied()[cells[:, 0], cells[:, 1]].all()


def test_sight_lines_clear_only_where_they_run_low() -> None:
    """A 0.45 m table 1 m from the camera, the floor seen beyond it 2.5-3.4 m away: the sight lines
    pass over the table 0.7 m high, which proves nothing about the table with ``clear_height``
    0.3 m; near their floor ends they run under it and clear those cells. Thin evidence (one point)
    marks no obstacle."""
    low = OccupancyConfig(clear_height=0.3)
    m = LogOddsMap(SPEC)
    table = (0.525, 1.025)
    cell = tuple(SPEC.world_to_cell(np.array(table)))
    _fuse(m, _cell_points(table, 0.45), (-0.5, 1.0), low)
    for _ in range(5):
        _fuse(m, _floor(2.0, 2.9, 1.025), (-0.5, 1.0), low)
    assert m.occupied()[cell]
    ends = SPEC.cell_to_world(np.argwhere(m.logodds < 0))[:, 0]
    assert ends.min() >= -0.5 + 0.75 * 2.5 - 0.05  # the lines drop under 0.3 m after 3/4 of the way
    lone = LogOddsMap(SPEC)
    _fuse(lone, [[2.0, 1.0, 0.5]], camera_xy=(0.0, 1.0))  # one point in its cell
    assert not lone.occupied().any()


def test_sight_lines_over_a_low_obstacle_do_not_clear_it() -> None:
    """A 0.45 m box 1 m from the camera, then the floor seen beyond it: the sight lines pass over
    the box about 0.7 m high, under the default ``clear_height`` (0.8 m) but above the box's
    highest fused point, so they prove nothing about it and it stays an obstacle; the same lines
    clear a cell that held only a prior (no point fused there), and a line under a fused phantom's
    top clears it."""
    box = (0.525, 1.025)
    cell = tuple(SPEC.world_to_cell(np.array(box)))
    m = LogOddsMap(SPEC)
    _fuse(m, np.concatenate([_cell_points(box, z) for z in (0.2, 0.3, 0.45)]), (-0.5, 1.0))
    assert m.occupied()[cell] and m.top[cell] == pytest.approx(0.45)
    for _ in range(5):
        _fuse(m, _floor(2.0, 2.9, 1.025), (-0.5, 1.0))
    assert m.occupied()[cell] and m.logodds[cell] >= 0.85
    prior = LogOddsMap.from_prior(SPEC, np.zeros(SPEC.shape))
    prior.logodds[cell] = 1.0
    assert prior.top[cell] == 0.0
    for _ in range(5):
        _fuse(prior, _floor(2.0, 2.9, 1.025), (-0.5, 1.0))
    assert not prior.occupied()[cell]
    tall = LogOddsMap(SPEC)
    _fuse(tall, _cell_points(box, 1.0), (-0.5, 1.0))  # a floating phantom 1 m high
    for _ in range(5):
        _fuse(tall, _floor(2.0, 2.9, 1.025), (-0.5, 1.0))
    assert not tall.occupied()[cell]


def test_floor_seen_needs_ground_points_not_sight_lines() -> None:
    """Sight lines over a cell make it free but not floor-seen; ground points in it in two frames
    do (what reopens a contact mark)."""
    m = LogOddsMap(SPEC)
    over = (0.525, 1.025)  # under the lines from the camera at x = -0.5 to the floor at 2-2.9 m
    cell = tuple(SPEC.world_to_cell(np.array(over)))
    for _ in range(5):
        _fuse(m, _floor(2.0, 2.9, 1.025), (-0.5, 1.0), OccupancyConfig(clear_height=1.2))
    assert m.free(0.2)[cell] and not m.floor_seen(0.2)[cell]
    _fuse(m, _floor(0.45, 0.6, 1.025), (-0.5, 1.0))
    assert not m.floor_seen(0.2)[cell]
    _fuse(m, _floor(0.45, 0.6, 1.025), (-0.5, 1.0))
    assert m.floor_seen(0.2)[cell]
    m.logodds = np.zeros(SPEC.shape, np.float32)  # a new episode
    assert not m.floor_frames.any()
