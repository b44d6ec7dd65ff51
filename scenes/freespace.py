"""Coarse free-space check on a spec's footprints: used by the procedural generator and the tests.

This is a fast 2D proxy (object footprints as rotated rectangles, walls as thick segments with door
gaps), not the ground truth (``vgpnav_env.groundtruth`` works on the meshes).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import cv2
import numpy as np
from numpy.typing import NDArray

from vgpnav_env.grid import GridSpec
from vgpnav_env.robot import OBSTACLE_MIN, ROBOT_RADIUS
from vgpnav_env.scenes.primitives import PRIMITIVES
from vgpnav_env.scenes.spec import ObjectSpec, SceneSpec, WallSpec

# Kinds that never block the robot (they lie flat on the floor or hang on walls).
PASSABLE_KINDS: frozenset[str] = frozenset({"rug", "picture", "poster", "panel"})


def footprint(o: ObjectSpec) -> NDArray[np.float64]:
    """Corners (4, 2) in W of an object's footprint rectangle."""
    w, d, _ = o.size if o.size is not None else PRIMITIVES[o.kind].size
    local = np.array([[-w / 2, -d / 2], [w / 2, -d / 2], [w / 2, d / 2], [-w / 2, d / 2]])
    c, s = math.cos(o.yaw), math.sin(o.yaw)
    return local @ np.array([[c, s], [-s, c]]) + (o.x, o.y)


def blocks(o: ObjectSpec, max_height: float = 1.5, min_height: float = OBSTACLE_MIN) -> bool:
    """Whether an object occupies the height band [min_height, max_height] the robot sweeps."""
    if o.kind in PASSABLE_KINDS:
        return False
    h = o.size[2] if o.size is not None else (PRIMITIVES[o.kind].size[2] if o.kind != "mesh" else 1.0)
    return o.z < max_height and o.z + h > min_height


def wall_rects(w: WallSpec) -> list[NDArray[np.float64]]:
    """Corner rectangles (4, 2) of a wall's floor-level solid pieces (door gaps left open)."""
    p0, p1 = np.asarray(w.start), np.asarray(w.end)
    t = (p1 - p0) / w.length
    nrm = np.array([-t[1], t[0]]) * w.thickness / 2
    cuts, a = [], 0.0
    for door in w.doors:
        cuts.append((a, door.at - door.width / 2))
        a = door.at + door.width / 2
    cuts.append((a, w.length))
    return [
        np.array([p0 + a0 * t - nrm, p0 + a1 * t - nrm, p0 + a1 * t + nrm, p0 + a0 * t + nrm])
        for a0, a1 in cuts
        if a1 > a0
    ]


def spec_grid(spec: SceneSpec, resolution: float) -> GridSpec:
    pts = np.concatenate([np.asarray(r.polygon) for r in spec.rooms])
    return GridSpec.covering(pts.min(axis=0), pts.max(axis=0), resolution, margin=0.3)


def _fill(mask: NDArray[np.uint8], grid: GridSpec, polys: Iterable[NDArray]) -> None:
    shift = 4
    for p in polys:
        px = (np.asarray(p) - grid.origin) / grid.resolution - 0.5
        cv2.fillPoly(
            mask, [np.round(px * (1 << shift)).astype(np.int32)], 1, lineType=cv2.LINE_8, shift=shift
        )


def navigable_grid(
    spec: SceneSpec,
    objects: Iterable[ObjectSpec],
    robot_radius: float = ROBOT_RADIUS,
    resolution: float = 0.05,
) -> tuple[GridSpec, NDArray[np.bool_], NDArray[np.bool_]]:
    """(grid, inside-rooms mask, navigable mask): free cells at least ``robot_radius`` from obstacles."""
    grid = spec_grid(spec, resolution)
    inside = np.zeros(grid.shape, np.uint8)
    _fill(inside, grid, (np.asarray(r.polygon) for r in spec.rooms))
    occ = np.zeros(grid.shape, np.uint8)
    _fill(occ, grid, (r for w in spec.walls for r in wall_rects(w)))
    _fill(occ, grid, (footprint(o) for o in objects if blocks(o)))
    free = ((inside > 0) & (occ == 0)).astype(np.uint8)
    dist = cv2.distanceTransform(free, cv2.DIST_L2, 5) * resolution
    return grid, inside > 0, dist > robot_radius


def connectivity_report(
    spec: SceneSpec,
    objects: Iterable[ObjectSpec],
    robot_radius: float = ROBOT_RADIUS,
    resolution: float = 0.05,
) -> tuple[list[str], float]:
    """(rooms with no navigable cell in the main component, fraction of navigable cells outside it)."""
    grid, _, nav = navigable_grid(spec, objects, robot_radius, resolution)
    n, labels = cv2.connectedComponents(nav.astype(np.uint8), connectivity=8)
    if n <= 1:
        return [r.name for r in spec.rooms], 1.0
    counts = np.bincount(labels.ravel())[1:]
    main = int(np.argmax(counts)) + 1
    lost = [r.name for r in spec.rooms if not _room_touches(grid, labels == main, r.polygon)]
    return lost, float(1.0 - counts.max() / counts.sum())


def _room_touches(grid: GridSpec, mask: NDArray[np.bool_], polygon: tuple[tuple[float, float], ...]) -> bool:
    room = np.zeros(grid.shape, np.uint8)
    _fill(room, grid, [np.asarray(polygon)])
    return bool(np.any(mask & (room > 0)))
