"""Ground truth from meshes: surface points, floor/obstacle/free/navigable grids, paths on them."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from conftest import ROOM_X, ROOM_Y, TINY_BOXES, WALL_H, WALL_T, textured_box

from vgpnav_env.envs.body import PlanarRobot, add_robot
from vgpnav_env.grid import erode, geodesic_distance, largest_component, path_length, shortest_path
from vgpnav_env.groundtruth import GroundTruthMap, ground_truth_map, surface_points
from vgpnav_env.scenes.model import build_mjspec
from vgpnav_env.scenes.scene import Scene, SceneMesh

# Radii that are not multiples of the 5 cm cells, so no cell centre sits exactly at the radius.
RADIUS = 0.22


def expected_navigable(radius: float, boxes: bool) -> float:
    """Room interior shrunk by the radius minus each box's Minkowski sum with the robot disc."""
    area = (ROOM_X - 2 * radius) * (ROOM_Y - 2 * radius)
    if boxes:
        for _, (w, d, _h) in TINY_BOXES.values():
            area -= w * d + 2 * radius * (w + d) + np.pi * radius**2
    return area


def boundary(radius: float, boxes: bool) -> float:
    """Length (m) of the boundary of the region of ``expected_navigable``."""
    length = 2 * (ROOM_X - 2 * radius) + 2 * (ROOM_Y - 2 * radius)
    if boxes:
        for _, (w, d, _h) in TINY_BOXES.values():
            length += 2 * (w + d) + 2 * np.pi * radius
    return length


def test_surface_points_density_and_bounds(tiny_scene):
    pts = surface_points(tiny_scene, spacing=0.05, seed=0)
    area = sum(m.mesh.area for m in tiny_scene.meshes)
    assert len(pts) == pytest.approx(area / 0.05**2, rel=0.01)
    lo, hi = tiny_scene.bounds
    assert np.all(pts >= lo - 1e-9) and np.all(pts <= hi + 1e-9)
    np.testing.assert_array_equal(pts, surface_points(tiny_scene, spacing=0.05, seed=0))
    # Every point lies on some mesh surface: the floor top is at z = 0, walls at x = 0 / 4 ...
    on_floor = np.abs(pts[:, 2]) < 1e-9
    assert on_floor.sum() > 0.5 * ROOM_X * ROOM_Y / 0.05**2
    no_floor = surface_points(tiny_scene, spacing=0.05, exclude_categories=("floor",))
    floor_area = tiny_scene.mesh("floor").mesh.area
    assert len(no_floor) == pytest.approx((area - floor_area) / 0.05**2, rel=0.01)


@pytest.mark.parametrize("radius", [0.18, RADIUS])
def test_navigable_area_empty_and_furnished(empty_room, tiny_scene, radius):
    for scene, boxes in ((empty_room, False), (tiny_scene, True)):
        gt = ground_truth_map(scene, robot_radius=radius)
        expected = expected_navigable(radius, boxes)
        # Cells count whole by their centre's exact clearance: the boundary sits up to half a cell
        # (0.025 m) off the exact one (here 0.02 m inwards at 0.18 m: -3%).
        assert gt.area_m2(gt.navigable) == pytest.approx(expected, abs=0.025 * boundary(radius, boxes))
        # Free = room interior minus box footprints, to within one boundary cell row (~4%).
        footprints = sum(w * d for _, (w, d, _h) in TINY_BOXES.values()) if boxes else 0.0
        assert gt.area_m2(gt.free) == pytest.approx(ROOM_X * ROOM_Y - footprints, rel=0.04)
        # The floor slab reaches under the walls (0.1 m thick all around).
        assert gt.area_m2(gt.floor) == pytest.approx((ROOM_X + 0.2) * (ROOM_Y + 0.2), rel=0.03)


def test_layers_consistent(tiny_scene):
    gt = ground_truth_map(tiny_scene, robot_radius=RADIUS)
    assert isinstance(gt, GroundTruthMap)
    np.testing.assert_array_equal(gt.free, gt.floor & ~gt.obstacle)
    assert not np.any(gt.navigable & ~gt.free)
    # Box footprints are obstacles; the room centre is navigable; the walls are obstacles.
    assert not gt.is_navigable(np.array([[1.0, 1.5], [3.0, 3.5], [-0.05, 2.5]])).any()
    assert gt.is_navigable(np.array([2.0, 2.5]))
    assert not gt.is_navigable(np.array([100.0, 100.0]))
    # Wall interiors (between the wall's faces) are obstacles, never enclosed free space.
    r, c = gt.spec.world_to_cell(np.array([-0.05, 2.5]))
    assert gt.obstacle[r, c] and not gt.free[r, c]
    # The cache returns the same object.
    assert ground_truth_map(tiny_scene, robot_radius=RADIUS) is gt


def test_obstacle_band(tiny_scene):
    """box_b is 0.5 m tall: no obstacle if the band starts above it; walls (2.5 m) still are."""
    gt = ground_truth_map(tiny_scene, robot_radius=RADIUS, obstacle_band=(0.6, None))
    assert gt.is_navigable(np.array([3.0, 3.5]))
    assert not gt.is_navigable(np.array([1.0, 1.5]))  # box_a is 0.8 m tall
    with pytest.raises(ValueError, match="obstacle_band"):
        ground_truth_map(tiny_scene, obstacle_band=(1.0, 0.5))
    assert WALL_H > 1.3


def test_thin_wall_does_not_leak(walled_room):
    """A 0.1 m wall at y = 2.5 from x = 0 to 3: paths and geodesics detour through the gap."""
    gt = ground_truth_map(walled_room, robot_radius=RADIUS)
    start, goal = (1.0, 1.5), (1.0, 3.5)
    path = shortest_path(gt.navigable, gt.spec, start, goal)
    assert path is not None
    detour = 2 * np.hypot(3.0 + RADIUS - 1.0, 1.0)  # around the wall end (x = 3) plus clearance
    assert path_length(path) > detour - 0.1
    dist = geodesic_distance(gt.navigable, gt.spec, goal)
    r, c = gt.spec.world_to_cell(np.array(start))
    assert dist[r, c] > 2.0 + 2.0  # Euclidean is 2 m
    # With the gap closed off by a radius too large to pass (gap is 1 m wide): unreachable.
    closed = ground_truth_map(walled_room, robot_radius=0.55)
    assert shortest_path(closed.navigable, closed.spec, start, goal) is None
    r, c = closed.spec.world_to_cell(np.array(start))
    assert np.isinf(geodesic_distance(closed.navigable, closed.spec, goal)[r, c])
    # Free space (radius 0) also stays split along the wall except through the gap.
    free_path = shortest_path(gt.free, gt.spec, start, goal)
    assert path_length(free_path) > 2 * np.hypot(2.0, 1.0) - 0.1


def test_gap_narrower_than_the_robot_is_not_navigable(empty_room):
    """A wall across y = 2.5 with a 0.352 m gap (x in [1.999, 2.351]), each face 1 mm inside a cell:
    the obstacle cell centres either side (x = 1.975, 2.375) are 0.4 m apart, so erosion from cell
    centres alone keeps the gap's middle column (x = 2.175) and joins the two halves, but a robot
    of radius 0.2 m does not fit. Navigable cells follow the collision parts: none is in contact."""
    wall = empty_room.mesh("wall_south").material
    parts = []
    for name, (x0, x1) in (("gap_left", (0.0, 1.999)), ("gap_right", (2.351, ROOM_X))):
        extents, centre = (x1 - x0, WALL_T, WALL_H), ((x0 + x1) / 2, 2.5, WALL_H / 2)
        box = trimesh.creation.box(
            extents=extents, transform=trimesh.transformations.translation_matrix(centre)
        )
        parts.append(SceneMesh(name, "wall", textured_box(extents, centre, wall), wall, [box]))
    scene = Scene("tiny", "gap", "checker", [*empty_room.meshes, *parts])
    gt = ground_truth_map(scene, robot_radius=0.2)
    start, goal = (1.0, 1.5), (1.0, 3.5)
    assert shortest_path(erode(gt.free, 0.2, gt.spec), gt.spec, start, goal) is not None
    assert shortest_path(gt.navigable, gt.spec, start, goal) is None
    # Away from the gap and the walls navigable is unchanged (room halves 4 x 2.45 m less 0.2 m).
    assert gt.area_m2(gt.navigable) == pytest.approx(2 * (ROOM_X - 0.4) * (2.45 - 0.4), rel=0.03)
    spec = build_mjspec(scene)
    add_robot(spec, radius=0.2, height=1.3)
    robot = PlanarRobot(spec.compile())
    centres = gt.spec.cell_to_world(np.argwhere(gt.navigable))
    assert not any(robot.in_collision([x, y, 0.0]) for x, y in centres)
    assert robot.in_collision([2.175, 2.5, 0.0])


def test_straight_path_in_empty_room(empty_room):
    gt = ground_truth_map(empty_room, robot_radius=RADIUS)
    for start, goal in (((0.5, 0.5), (3.5, 4.5)), ((0.6, 2.0), (3.4, 2.3))):
        path = shortest_path(gt.navigable, gt.spec, start, goal)
        euclid = float(np.linalg.norm(np.subtract(goal, start)))
        assert path_length(path) == pytest.approx(euclid, rel=0.02)


def test_largest_component_is_one_region(walled_room):
    gt = ground_truth_map(walled_room, robot_radius=0.55)
    big = largest_component(gt.navigable)
    assert 0 < big.sum() < gt.navigable.sum()  # the room splits in two; keep the larger side


def test_home_ground_truth_is_plausible():
    from vgpnav_env.scenes import load_scene

    gt = ground_truth_map(load_scene("home"))
    floor, free, nav = (gt.area_m2(m) for m in (gt.floor, gt.free, gt.navigable))
    big = gt.area_m2(largest_component(gt.navigable))
    print(f"home: floor {floor:.1f}, free {free:.1f}, navigable {nav:.1f}, largest region {big:.1f} m2")
    assert 80.0 <= floor <= 120.0  # DESIGN: ~80-120 m2 apartment
    assert 0.3 * floor <= nav < free < floor
    assert big >= 0.9 * nav  # rooms connect through doors
