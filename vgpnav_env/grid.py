"""The one 2D grid type over the floor plane of W (metres), shared by ground truth and maps.

Cell (row, col) covers x in [x0 + col*res, x0 + (col+1)*res) and y in [y0 + row*res, ...):
rows grow along +y, columns along +x (so ``array[row, col]``; flip rows to draw north-up).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray


@dataclass(frozen=True)
class GridSpec:
    """Geometry of a 2D grid: ``origin`` = world (x, y) of the corner of cell (0, 0)."""

    origin: tuple[float, float]
    resolution: float
    shape: tuple[int, int]  # (rows along y, cols along x)

    def __post_init__(self) -> None:
        if self.resolution <= 0:
            raise ValueError(f"grid resolution must be positive metres, got {self.resolution}")
        if min(self.shape) <= 0:
            raise ValueError(f"grid shape must be positive, got {self.shape}")

    @classmethod
    def covering(
        cls, xy_min: ArrayLike, xy_max: ArrayLike, resolution: float, margin: float = 0.0
    ) -> GridSpec:
        """Smallest grid with the given resolution covering the box [xy_min, xy_max] + margin."""
        lo = np.asarray(xy_min, float) - margin
        hi = np.asarray(xy_max, float) + margin
        cols, rows = np.maximum(np.ceil((hi - lo) / resolution).astype(int), 1)
        return cls((float(lo[0]), float(lo[1])), float(resolution), (int(rows), int(cols)))

    @property
    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """World (x, y) of the grid's two corners: (min, max) in metres."""
        lo = np.asarray(self.origin, float)
        return lo, lo + np.asarray(self.shape[::-1], float) * self.resolution

    @property
    def centre(self) -> NDArray[np.float64]:
        """World (x, y) of the grid's centre (metres)."""
        lo, hi = self.bounds
        return 0.5 * (lo + hi)

    def world_to_cell(self, xy: ArrayLike) -> NDArray[np.int64]:
        """Integer (row, col) of world points (..., 2); may be out of bounds (see ``contains``)."""
        xy = np.asarray(xy, float)
        col = np.floor((xy[..., 0] - self.origin[0]) / self.resolution)
        row = np.floor((xy[..., 1] - self.origin[1]) / self.resolution)
        return np.stack([row, col], axis=-1).astype(np.int64)

    def cell_to_world(self, cells: ArrayLike) -> NDArray[np.float64]:
        """World (x, y) of cell centres for (..., 2) integer (row, col)."""
        rc = np.asarray(cells, float)
        x = self.origin[0] + (rc[..., 1] + 0.5) * self.resolution
        y = self.origin[1] + (rc[..., 0] + 0.5) * self.resolution
        return np.stack([x, y], axis=-1)

    def contains(self, cells: ArrayLike) -> NDArray[np.bool_]:
        """Whether (..., 2) integer (row, col) lie inside the grid."""
        rc = np.asarray(cells)
        return (
            (rc[..., 0] >= 0)
            & (rc[..., 0] < self.shape[0])
            & (rc[..., 1] >= 0)
            & (rc[..., 1] < self.shape[1])
        )

    def centres(self) -> NDArray[np.float64]:
        """World (x, y) of every cell centre, shape (rows, cols, 2)."""
        rows, cols = np.meshgrid(np.arange(self.shape[0]), np.arange(self.shape[1]), indexing="ij")
        return self.cell_to_world(np.stack([rows, cols], axis=-1))


def _check_mask(mask: ArrayLike, spec: GridSpec, name: str) -> NDArray[np.bool_]:
    mask = np.asarray(mask)
    if mask.shape != spec.shape:
        raise ValueError(f"{name} has shape {mask.shape}, but the grid spec has shape {spec.shape}")
    return mask.astype(bool, copy=False)


def cell_of(spec: GridSpec, xy: ArrayLike, what: str = "point") -> tuple[int, int]:
    """(row, col) of one world point; a clear error if it lies off the grid."""
    xy = np.asarray(xy, float)
    if xy.shape != (2,) or not np.all(np.isfinite(xy)):
        raise ValueError(f"{what} must be a finite world (x, y), got {xy!r}")
    cell = spec.world_to_cell(xy)
    if not spec.contains(cell):
        lo, hi = spec.bounds
        raise ValueError(
            f"{what} {tuple(xy)} is off the grid (x in [{lo[0]}, {hi[0]}), y in [{lo[1]}, {hi[1]}))"
        )
    return int(cell[0]), int(cell[1])


def _mcp(traversable: NDArray[np.bool_], cost: NDArray[np.float64] | None = None):
    from skimage.graph import MCP_Geometric

    costs = np.where(traversable, 1.0 if cost is None else cost, np.inf)
    return MCP_Geometric(costs, fully_connected=True)


def geodesic_distance(traversable: ArrayLike, spec: GridSpec, goal_xy: ArrayLike) -> NDArray[np.float64]:
    """Metres (rows, cols) from every cell to ``goal_xy`` moving 8-connected through traversable
    cells (octile metric: straight steps = resolution, diagonal = sqrt(2) * resolution); ``inf``
    where unreachable, also everywhere if the goal cell is not traversable."""
    traversable = _check_mask(traversable, spec, "traversable")
    goal = cell_of(spec, goal_xy, "goal")
    if not traversable[goal]:
        return np.full(spec.shape, np.inf)
    cumulative, _ = _mcp(traversable).find_costs([goal])
    return np.where(traversable, cumulative * spec.resolution, np.inf)


def line_of_sight(traversable: NDArray[np.bool_], spec: GridSpec, a_xy: ArrayLike, b_xy: ArrayLike) -> bool:
    """Whether the straight segment a -> b (world xy) crosses only traversable cells."""
    a, b = np.asarray(a_xy, float), np.asarray(b_xy, float)
    n = max(2, int(np.ceil(4.0 * np.linalg.norm(b - a) / spec.resolution)) + 1)
    cells = spec.world_to_cell(a + np.linspace(0.0, 1.0, n)[:, None] * (b - a))
    inside = spec.contains(cells)
    return bool(np.all(inside) and np.all(traversable[cells[:, 0], cells[:, 1]]))


def _segment_cost(cost: NDArray[np.float64], spec: GridSpec, a: NDArray, b: NDArray) -> float:
    """The highest cell cost on the straight segment a -> b (world xy)."""
    n = max(2, int(np.ceil(4.0 * np.linalg.norm(b - a) / spec.resolution)) + 1)
    cells = spec.world_to_cell(a + np.linspace(0.0, 1.0, n)[:, None] * (b - a))
    return float(cost[cells[:, 0], cells[:, 1]].max())


def _shortcut(
    traversable: NDArray[np.bool_],
    spec: GridSpec,
    path: NDArray[np.float64],
    cost: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """Greedy string pulling: from each kept vertex, jump to the farthest vertex still in sight
    (with ``cost``: through no cell costlier than the costliest cell of the path it replaces, so a
    shortcut never brings the path nearer to obstacles than the planned path went)."""
    if cost is not None:
        on_path = cost[tuple(spec.world_to_cell(path).T)]
    kept = [0]
    i = 0
    while i < len(path) - 1:
        j = i + 1
        while j + 1 < len(path) and line_of_sight(traversable, spec, path[i], path[j + 1]):
            if cost is not None:
                if _segment_cost(cost, spec, path[i], path[j + 1]) > on_path[i : j + 2].max():
                    break
            j += 1
        kept.append(j)
        i = j
    return path[kept]


def shortest_path(
    traversable: ArrayLike,
    spec: GridSpec,
    start_xy: ArrayLike,
    goal_xy: ArrayLike,
    *,
    smooth: bool = True,
    cost: ArrayLike | None = None,
) -> NDArray[np.float64] | None:
    """Shortest 8-connected path (N, 2) of world xy from ``start_xy`` to ``goal_xy`` on a boolean grid.

    The path starts at ``start_xy`` and ends at ``goal_xy`` exactly, through cell centres in
    between; ``smooth`` removes vertices while the straight segments stay on traversable cells
    (so straight corridors give straight lines, not octile zig-zags). ``cost``: an optional
    per-cell cost (>= 1, ``spec.shape``) multiplying the length of the steps through the cell (a
    costmap: the path is the cheapest, not the shortest), which the smoothing respects too. None if
    the start or goal cell is not traversable or no path exists; ValueError if either lies off the
    grid.
    """
    traversable = _check_mask(traversable, spec, "traversable")
    start = cell_of(spec, start_xy, "start")
    goal = cell_of(spec, goal_xy, "goal")
    if not (traversable[start] and traversable[goal]):
        return None
    if cost is not None:
        cost = np.asarray(cost, float)
        if cost.shape != spec.shape or np.any(cost[traversable] < 1.0):
            raise ValueError(f"cost must be >= 1 on traversable cells with shape {spec.shape}")
    mcp = _mcp(traversable, cost)
    cumulative, _ = mcp.find_costs([start], [goal])
    if not np.isfinite(cumulative[goal]):
        return None
    cells = np.asarray(mcp.traceback(goal))
    path = spec.cell_to_world(cells if len(cells) > 1 else np.repeat(cells, 2, axis=0))
    path[0], path[-1] = np.asarray(start_xy, float), np.asarray(goal_xy, float)
    return _shortcut(traversable, spec, path, cost) if smooth else path


def path_length(path: ArrayLike) -> float:
    """Length (metres) of a polyline (N, 2)."""
    path = np.asarray(path, float)
    return float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())


def erode(mask: ArrayLike, radius_m: float, spec: GridSpec) -> NDArray[np.bool_]:
    """Cells of ``mask`` whose centre is at least ``radius_m`` from every cell centre outside it.

    Centre-to-centre distance is an unbiased estimate of the clearance to a surface that lies
    somewhere inside the nearest outside cell (the true clearance may be up to half a cell
    less). The grid border counts as outside. E.g. free space eroded by the robot radius keeps
    the cells where a disc robot fits.
    """
    mask = _check_mask(mask, spec, "mask")
    if radius_m < 0:
        raise ValueError(f"radius_m must be >= 0 metres, got {radius_m}")
    return mask & (clearance(mask, spec) >= radius_m - 1e-9)


def clearance(mask: ArrayLike, spec: GridSpec) -> NDArray[np.float64]:
    """Metres from every ``mask`` cell centre to the nearest cell centre outside it (0 outside);
    the grid border counts as outside."""
    from scipy.ndimage import distance_transform_edt

    padded = np.pad(_check_mask(mask, spec, "mask"), 1, constant_values=False)
    return distance_transform_edt(padded)[1:-1, 1:-1] * spec.resolution


def nearest_true_cell(mask: ArrayLike, cell: ArrayLike) -> tuple[int, int] | None:
    """The True cell (row, col) of ``mask`` nearest to ``cell`` (Euclidean in cells); None if none."""
    candidates = np.argwhere(np.asarray(mask, bool))
    if len(candidates) == 0:
        return None
    d2 = ((candidates - np.asarray(cell)) ** 2).sum(axis=1)
    r, c = candidates[int(np.argmin(d2))]
    return int(r), int(c)


def largest_component(mask: ArrayLike) -> NDArray[np.bool_]:
    """The largest 8-connected component of a boolean grid (all False if the grid is empty)."""
    from scipy.ndimage import label

    mask = np.asarray(mask, bool)
    labels, n = label(mask, structure=np.ones((3, 3), int))
    if n == 0:
        return np.zeros_like(mask)
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    return labels == int(np.argmax(sizes))
