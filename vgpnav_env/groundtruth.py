"""Ground truth from a scene's meshes: dense surface points and the 2D navigation grid.

Occupancy by height (DESIGN.md): a cell is an *obstacle* if any surface lies above it at a
height in the obstacle band (by default the robot's: ``vgpnav_env.robot.OBSTACLE_MIN`` = 0.15 m to
the robot height); it is *floor* if an upward-facing surface lies within ``floor_tolerance`` of
z = 0 over it; *free* = floor and not obstacle; *navigable* = free cells where the robot disc
fits: free eroded by the robot radius (cell centre to cell centre) whose centre also lies at least
the robot radius from the exact footprint of every convex collision part in the band (the geometry
MuJoCo collides the robot's cylinder with), so no navigable cell puts the robot in contact.

Obstacles come from two sources: densely sampled surfaces (several points per cell even on
thin vertical walls, so walls are continuous obstacle lines) and the filled footprints of the
scene's convex collision parts within the band (so the inside of a wall or of a tall closed
cabinet is an obstacle too, not enclosed "free" space). The floor is sampled denser still and
pin-holes of one or two cells are closed so that sampling never punches holes into it.
"""

from __future__ import annotations

import logging
import time
import weakref
from dataclasses import dataclass

import numpy as np
import trimesh
from numpy.typing import NDArray

from vgpnav_env.grid import GridSpec, erode, largest_component
from vgpnav_env.robot import FLOOR_TOLERANCE, OBSTACLE_MIN, ROBOT_HEIGHT, ROBOT_RADIUS
from vgpnav_env.scenes.scene import Scene

logger = logging.getLogger(__name__)

__all__ = ["GroundTruthMap", "ground_truth_map", "largest_component", "surface_points"]


def _sample(mesh: trimesh.Trimesh, spacing: float, rng: np.random.Generator, faces=None):
    """Area-proportional random surface samples (points, face indices) with ~1 point per spacing^2."""
    faces = np.arange(len(mesh.faces)) if faces is None else np.asarray(faces)
    if len(faces) == 0:
        return np.zeros((0, 3)), np.zeros(0, int)
    areas = mesh.area_faces[faces]
    total = float(areas.sum())
    count = int(np.ceil(total / spacing**2))
    if count == 0:
        return np.zeros((0, 3)), np.zeros(0, int)
    chosen = faces[rng.choice(len(faces), size=count, p=areas / total)]
    tri = mesh.triangles[chosen]
    r = rng.random((count, 2))
    flip = r.sum(axis=1) > 1.0
    r[flip] = 1.0 - r[flip]
    points = tri[:, 0] + r[:, :1] * (tri[:, 1] - tri[:, 0]) + r[:, 1:] * (tri[:, 2] - tri[:, 0])
    return points, chosen


def surface_points(
    scene: Scene, spacing: float = 0.02, seed: int = 0, exclude_categories: tuple[str, ...] = ()
) -> NDArray[np.float64]:
    """Dense surface sample (N, 3) in W of the scene's meshes, ~one point per ``spacing``^2 of area.

    ``exclude_categories`` drops meshes by ``SceneMesh.category`` (e.g. ``("ceiling",)``).
    """
    if spacing <= 0:
        raise ValueError(f"spacing must be positive metres, got {spacing}")
    rng = np.random.default_rng(seed)
    parts = [
        _sample(sm.mesh, spacing, rng)[0] for sm in scene.meshes if sm.category not in exclude_categories
    ]
    return np.concatenate(parts, axis=0) if parts else np.zeros((0, 3))


@dataclass(frozen=True)
class GroundTruthMap:
    """Boolean (rows, cols) layers over ``spec`` (see module doc) and the parameters used."""

    spec: GridSpec
    floor: NDArray[np.bool_]
    obstacle: NDArray[np.bool_]
    free: NDArray[np.bool_]
    navigable: NDArray[np.bool_]
    robot_radius: float
    robot_height: float
    obstacle_band: tuple[float, float]

    def area_m2(self, mask: NDArray[np.bool_]) -> float:
        """Area (m^2) of the True cells of a mask over this grid."""
        mask = np.asarray(mask, bool)
        if mask.shape != self.spec.shape:
            raise ValueError(f"mask shape {mask.shape} does not match the grid {self.spec.shape}")
        return float(mask.sum()) * self.spec.resolution**2

    def is_navigable(self, xy) -> NDArray[np.bool_]:
        """Whether world points (..., 2) lie on navigable cells (False off the grid)."""
        cells = self.spec.world_to_cell(xy)
        inside = self.spec.contains(cells)
        out = np.zeros(inside.shape, bool)
        out[inside] = self.navigable[cells[inside][:, 0], cells[inside][:, 1]]
        return out


def _bin(spec: GridSpec, points_xy: NDArray[np.float64]) -> NDArray[np.bool_]:
    grid = np.zeros(spec.shape, bool)
    cells = spec.world_to_cell(points_xy)
    inside = spec.contains(cells)
    grid[cells[inside, 0], cells[inside, 1]] = True
    return grid


def _slab_footprint(part: trimesh.Trimesh, low: float, high: float) -> NDArray[np.float64]:
    """xy points whose convex hull is the footprint of a convex part cut to low <= z <= high."""
    v = np.asarray(part.vertices, float)
    pts = [v[(v[:, 2] >= low) & (v[:, 2] <= high)]]
    e = v[part.edges_unique]
    za, zb = e[:, 0, 2], e[:, 1, 2]
    for c in (low, high):
        m = (np.minimum(za, zb) < c) & (np.maximum(za, zb) > c)
        t = (c - za[m]) / (zb[m] - za[m])
        pts.append(e[m, 0] + t[:, None] * (e[m, 1] - e[m, 0]))
    return np.concatenate(pts, axis=0)[:, :2]


def _footprint_hull(xy: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """Counter-clockwise vertices (K, 2) of the convex hull of ``xy``; for a flat footprint (zero
    area) its two extreme points (K = 2, a segment); None without points."""
    from scipy.spatial import ConvexHull, QhullError

    if len(xy) == 0:
        return None
    if len(xy) >= 3:
        try:
            return xy[ConvexHull(xy).vertices]
        except QhullError:
            pass
    d = xy - xy.mean(axis=0)
    t = d @ np.linalg.svd(d, full_matrices=False)[2][0]
    return xy[[int(np.argmin(t)), int(np.argmax(t))]]


def _window(spec: GridSpec, hull: NDArray[np.float64], margin: float) -> tuple[NDArray, NDArray] | None:
    """(rows, cols) index grids of the cells around ``hull`` grown by ``margin`` metres (None: off grid)."""
    (r0, c0), (r1, c1) = (
        spec.world_to_cell(hull.min(axis=0) - margin),
        spec.world_to_cell(hull.max(axis=0) + margin),
    )
    r0, c0 = max(r0, 0), max(c0, 0)
    r1, c1 = min(r1, spec.shape[0] - 1), min(c1, spec.shape[1] - 1)
    if r1 < r0 or c1 < c0:
        return None
    return np.mgrid[r0 : r1 + 1, c0 : c1 + 1]


def _fill_convex(spec: GridSpec, hull: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Cells whose centre lies inside (or on) a convex polygon (K >= 3 vertices; a segment fills nothing:
    its surface points mark it already)."""
    from matplotlib.path import Path

    grid = np.zeros(spec.shape, bool)
    window = _window(spec, hull, 0.0)
    if len(hull) < 3 or window is None:
        return grid
    rows, cols = window
    centres = spec.cell_to_world(np.stack([rows.ravel(), cols.ravel()], axis=1))
    inside = Path(hull).contains_points(centres, radius=1e-9)
    grid[rows.ravel()[inside], cols.ravel()[inside]] = True
    return grid


def _clear_of(spec: GridSpec, hulls: list[NDArray[np.float64]], radius: float) -> NDArray[np.bool_]:
    """Cells whose centre is at least ``radius`` metres (exactly, not cell-to-cell) from every convex
    footprint of ``hulls`` (counter-clockwise (K, 2) vertices, K = 2 a segment): where the robot disc
    touches no collision part."""
    clear = np.ones(spec.shape, bool)
    for hull in hulls:
        window = _window(spec, hull, radius)
        if window is None:
            continue
        rows, cols = window
        p = spec.cell_to_world(np.stack([rows, cols], axis=-1))[..., None, :]  # (h, w, 1, 2)
        a, b = hull, np.roll(hull, -1, axis=0)
        ab = b - a
        t = np.clip(np.sum((p - a) * ab, axis=-1) / np.maximum(np.sum(ab * ab, axis=-1), 1e-12), 0.0, 1.0)
        dist = np.linalg.norm(p - (a + t[..., None] * ab), axis=-1).min(axis=-1)
        if len(hull) >= 3:
            cross = ab[:, 0] * (p[..., 1] - a[:, 1]) - ab[:, 1] * (p[..., 0] - a[:, 0])
            dist[(cross >= 0.0).all(axis=-1)] = 0.0
        clear[rows, cols] &= dist >= radius
    return clear


def _close_pinholes(mask: NDArray[np.bool_], max_cells: int = 2) -> NDArray[np.bool_]:
    """Fill holes of at most ``max_cells`` cells (4-connected) fully enclosed by ``mask``."""
    from scipy.ndimage import label

    holes, n = label(~mask)
    if n == 0:
        return mask
    sizes = np.bincount(holes.ravel())
    small = sizes <= max_cells
    small[0] = False
    return mask | small[holes]


#: Per Scene object (by identity: hand-made scenes may share a ``key``), per parameters.
_GT_CACHE: weakref.WeakKeyDictionary[Scene, dict[tuple, GroundTruthMap]] = weakref.WeakKeyDictionary()


def ground_truth_map(
    scene: Scene,
    resolution: float = 0.05,
    robot_radius: float = ROBOT_RADIUS,
    robot_height: float = ROBOT_HEIGHT,
    obstacle_band: tuple[float, float | None] = (OBSTACLE_MIN, None),
    *,
    floor_tolerance: float = FLOOR_TOLERANCE,
    seed: int = 0,
) -> GroundTruthMap:
    """Occupancy, floor, free and navigable grids of ``scene`` (cached in-process).

    ``obstacle_band`` = (low, high) heights in metres; high None means ``robot_height``. The grid
    covers the scene's xy bounds plus a margin of two cells, with its origin on a multiple of
    ``resolution`` (so maps of one scene at one resolution share cells).
    """
    low, high = obstacle_band
    high = robot_height if high is None else high
    if resolution <= 0 or robot_radius < 0 or not 0 <= low < high:
        raise ValueError(
            f"need resolution > 0, robot_radius >= 0 and 0 <= band low < high; got resolution={resolution}, "
            f"robot_radius={robot_radius}, obstacle_band=({low}, {high})"
        )
    key = (resolution, robot_radius, robot_height, low, high, floor_tolerance, seed)
    cached = _GT_CACHE.setdefault(scene, {}).get(key)
    if cached is not None:
        return cached

    t0 = time.perf_counter()
    lo, hi = scene.bounds
    origin = np.floor(lo[:2] / resolution) * resolution - 2 * resolution
    size = np.ceil((hi[:2] + 2 * resolution - origin) / resolution).astype(int)
    spec = GridSpec((float(origin[0]), float(origin[1])), float(resolution), (int(size[1]), int(size[0])))

    rng = np.random.default_rng(seed)
    # Obstacles: ~10 points per cell on horizontal faces, more on vertical ones (taller extent).
    band_spacing = resolution / 3.0
    floor_spacing = resolution / 4.0
    obstacle = np.zeros(spec.shape, bool)
    floor = np.zeros(spec.shape, bool)
    hulls: list[NDArray[np.float64]] = []
    for sm in scene.meshes:
        mesh = sm.mesh
        z = mesh.triangles[:, :, 2]
        in_band = np.flatnonzero((z.max(axis=1) >= low) & (z.min(axis=1) <= high))
        points, _ = _sample(mesh, band_spacing, rng, in_band)
        points = points[(points[:, 2] >= low) & (points[:, 2] <= high)]
        obstacle |= _bin(spec, points[:, :2])
        for part in sm.collision:
            zmin, zmax = part.bounds[:, 2]
            if zmax >= low and zmin <= high:
                hull = _footprint_hull(_slab_footprint(part, low, high))
                if hull is not None:
                    hulls.append(hull)
                    obstacle |= _fill_convex(spec, hull)
        flat_up = mesh.face_normals[:, 2] > 0.9
        near_zero = (np.abs(z) <= floor_tolerance).all(axis=1)
        points, _ = _sample(mesh, floor_spacing, rng, np.flatnonzero(flat_up & near_zero))
        floor |= _bin(spec, points[:, :2])
    floor = _close_pinholes(floor)
    free = floor & ~obstacle
    navigable = erode(free, robot_radius, spec) & _clear_of(spec, hulls, robot_radius)
    gt = GroundTruthMap(spec, floor, obstacle, free, navigable, robot_radius, robot_height, (low, high))
    logger.info(
        "ground truth %s: %d x %d cells, navigable %.1f m^2 (%.2f s)",
        scene.key,
        *spec.shape,
        gt.area_m2(navigable),
        time.perf_counter() - t0,
    )
    _GT_CACHE[scene][key] = gt
    return gt
