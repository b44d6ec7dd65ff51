"""Metric occupancy from world points: height classes and a log-odds grid fused over time.

Points are metric world points (W, z up). Relative to the anchored ground height
``z_ground``: ``|z - z_ground| < free_tol`` is traversable ground (free);
``obstacle_min <= z - z_ground <= camera_height`` is an obstacle, projected onto the floor
grid (:class:`vgpnav_env.grid.GridSpec`, rows along +y, cols along +x).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import map_coordinates

from vgpnav_env.grid import GridSpec
from vgpnav_env.robot import FLOOR_TOLERANCE, OBSTACLE_MIN

#: Egocentric crop encoding.
UNKNOWN, FREE, OCCUPIED = 0, 128, 255


@dataclass(frozen=True)
class PointClasses:
    """Boolean masks (N,) over the input points."""

    free: NDArray[np.bool_]
    obstacle: NDArray[np.bool_]


@dataclass(frozen=True)
class OccupancyConfig:
    """Height classes (metres above the anchored ground), the points used and the log-odds fusion.

    Obstacles lie between ``obstacle_min`` and the camera height (paper); ground points within
    ``free_tol``. Only pixels with depth confidence >= ``min_confidence`` and metric depth <=
    ``max_depth`` are used, every ``point_stride``-th pixel in both directions. A
    :class:`LogOddsMap` adds ``l_occ`` / ``l_free`` per frame and clamps to ``clamp`` (the
    defaults of every map; the perceiver's maps take them from its config).

    What a frame's points may say (:meth:`LogOddsMap.update`): ``clear_height``, free evidence
    along each point's sight line from the camera where the line runs at most that high above the
    ground (None: 2D rays to the obstacle cells); obstacle cells need ``min_cell_points`` points of
    the frame and lie within ``max_obstacle_range`` m of the camera (far depth is the noisiest);
    ``protect_free``: one frame cannot turn a cell seen free into an obstacle. ``prior_weight``
    scales the database prior's log-odds (already a weak belief, clamped to
    :attr:`~vgpnav_env.perception.database.DatabaseConfig.prior_clamp`: free evidence overrides
    it within a few frames where the layout changed; at 0.5 the walls' weaker prior cells fell
    under the occupied threshold and a robot starting beside a wall bumped into it).
    """

    free_tol: float = FLOOR_TOLERANCE
    obstacle_min: float = OBSTACLE_MIN
    min_confidence: float = 0.2
    max_depth: float = 5.0
    point_stride: int = 2
    l_free: float = -0.4
    l_occ: float = 0.85
    clamp: tuple[float, float] = (-4.0, 4.0)
    clear_height: float | None = 0.8
    min_cell_points: int = 2
    max_obstacle_range: float | None = None
    protect_free: bool = True
    prior_weight: float = 1.0

    def __post_init__(self) -> None:
        if self.point_stride < 1:
            raise ValueError(f"point_stride must be >= 1, got {self.point_stride}")
        if self.free_tol <= 0 or self.obstacle_min <= 0 or self.max_depth <= 0:
            raise ValueError("free_tol, obstacle_min and max_depth must be positive metres")
        if not 0.0 <= self.min_confidence <= 1.0:
            raise ValueError(f"min_confidence must be in [0, 1], got {self.min_confidence}")
        if self.min_cell_points < 1 or self.prior_weight < 0:
            raise ValueError("min_cell_points must be >= 1 and prior_weight >= 0")


def classify_points(
    points_w: ArrayLike,
    z_ground: float,
    camera_height: float,
    free_tol: float = FLOOR_TOLERANCE,
    obstacle_min: float = OBSTACLE_MIN,
) -> PointClasses:
    """Free-ground and obstacle masks of world points (N, 3) by height above ``z_ground`` (m)."""
    P = np.asarray(points_w, float).reshape(-1, 3)
    dz = P[:, 2] - z_ground
    finite = np.isfinite(P).all(axis=1)
    return PointClasses(
        free=finite & (np.abs(dz) < free_tol),
        obstacle=finite & (dz >= obstacle_min) & (dz <= camera_height),
    )


def _unique_cells(spec: GridSpec, xy: NDArray[np.float64], min_count: int = 1) -> NDArray[np.int64]:
    """Flat indices of the distinct in-grid cells hit by at least ``min_count`` world points (N, 2)."""
    cells = spec.world_to_cell(xy)
    cells = cells[spec.contains(cells)]
    flat, counts = np.unique(cells[:, 0] * spec.shape[1] + cells[:, 1], return_counts=True)
    return flat[counts >= min_count]


def _sight_line_cells(
    spec: GridSpec,
    camera_xy: NDArray[np.float64],
    camera_z: float,
    points: NDArray[np.float64],
    height: float,
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Flat indices of the cells under the sight lines from a camera (``camera_xy``, ``camera_z``
    m above the ground) to points (N, 3: x, y and height above the ground) where a line runs at
    most ``height`` m above the ground, the points' own cells excluded, and the lowest height (m)
    a line runs at over each: what the line passing there proves free of obstacles taller than
    that (it reached the point). One line per distinct cell of the points (its lowest point)."""
    W = spec.shape[1]
    none = np.zeros(0, np.int64), np.zeros(0, float)
    cells = spec.world_to_cell(points[:, :2])
    inside = spec.contains(cells)
    flat, z = cells[inside, 0] * W + cells[inside, 1], points[inside, 2]
    if len(flat) == 0:
        return none
    order = np.lexsort((z, flat))
    first = np.r_[True, flat[order][1:] != flat[order][:-1]]
    flat, z = flat[order][first], z[order][first]
    low = z < min(height, camera_z)
    if not low.any():
        return none
    flat, z = flat[low], z[low]
    start = np.asarray(camera_xy, float)
    ends = spec.cell_to_world(np.stack([flat // W, flat % W], axis=1))
    t0 = np.clip((camera_z - height) / (camera_z - z), 0.0, 1.0)  # where the line drops to ``height``
    length = np.linalg.norm(ends - start, axis=1) / spec.resolution
    n = np.ceil(length * (1.0 - t0)).astype(int) + 1
    steps = int(n.max())
    u = np.arange(steps)[None, :] / np.maximum(n - 1, 1)[:, None]  # (lines, steps) in [0, 1]
    t = t0[:, None] + u * (1.0 - t0)[:, None]
    keep = (np.arange(steps)[None, :] < n[:, None]) & (t < 1.0)
    xy = start + t[..., None] * (ends - start)[:, None, :]
    line_z = camera_z + t * (z - camera_z)[:, None]
    on, on_z = spec.world_to_cell(xy[keep]), line_z[keep]
    inside = spec.contains(on)
    on_flat, on_z = on[inside, 0] * W + on[inside, 1], on_z[inside]
    mine = ~np.isin(on_flat, flat)
    on_flat, on_z = on_flat[mine], on_z[mine]
    order = np.lexsort((on_z, on_flat))
    first = np.r_[True, on_flat[order][1:] != on_flat[order][:-1]] if len(order) else np.zeros(0, bool)
    return on_flat[order][first], on_z[order][first]


def _farthest_per_direction(start: NDArray[np.int64], ends: NDArray[np.int64]) -> NDArray[np.int64]:
    """The farthest of ``ends`` (m, 2) in each direction bin seen from ``start``.

    Bins are one cell wide at the farthest end, so the rays to the dropped (nearer) ends
    are covered, to within a cell, by the kept ones.
    """
    d = (ends - start).astype(float)
    dist = np.hypot(d[:, 0], d[:, 1])
    n_bins = max(8, int(np.ceil(2.0 * np.pi * dist.max())))
    b = np.floor((np.arctan2(d[:, 0], d[:, 1]) + np.pi) / (2.0 * np.pi) * n_bins).astype(np.int64) % n_bins
    order = np.lexsort((-dist, b))  # by bin, farthest first
    first = np.r_[True, b[order][1:] != b[order][:-1]]
    return ends[order[first]]


def _ray_cells(start: NDArray[np.int64], ends: NDArray[np.int64]) -> NDArray[np.int64]:
    """(row, col) of the cells on the 2D segments start -> each end, ends excluded (DDA sampling)."""
    delta = ends - start
    n = np.abs(delta).max(axis=1)
    steps = int(n.max()) if len(n) else 0
    if steps == 0:
        return np.zeros((0, 2), np.int64)
    t = np.arange(steps)[None, :] / np.maximum(n, 1)[:, None]  # (rays, steps), t < 1 excludes the end
    pts = np.rint(start[None, None, :] + t[..., None] * delta[:, None, :]).astype(np.int64)
    keep = np.arange(steps)[None, :] < n[:, None]
    return pts[keep]


class LogOddsMap:
    """A log-odds occupancy grid (float32, 0 = unknown) over ``spec``.

    ``update`` adds ``l_occ`` once per cell with obstacle points in this frame and
    ``l_free`` once per cell with ground points or crossed by a 2D ray from the camera to an
    obstacle cell (when ``camera_xy`` is given; rays go to the farthest obstacle cell per
    one-cell-wide direction bin, which keeps the carving cheap), never to a cell hit by an obstacle in the
    same frame; values are clamped to ``clamp``. :attr:`top` holds per cell the height (m above the
    ground) of the highest obstacle point fused there (0: none), :attr:`floor_frames` in how many
    frames ground points fell in it (the floor seen there, not only sight lines over it); setting
    :attr:`logodds` (a prior, a new episode) forgets both.
    """

    def __init__(
        self,
        spec: GridSpec,
        l_free: float = OccupancyConfig.l_free,
        l_occ: float = OccupancyConfig.l_occ,
        clamp: tuple[float, float] = OccupancyConfig.clamp,
    ) -> None:
        if l_free >= 0 or l_occ <= 0:
            raise ValueError(f"need l_free < 0 < l_occ, got l_free={l_free}, l_occ={l_occ}")
        if not clamp[0] < 0 < clamp[1]:
            raise ValueError(f"clamp must satisfy low < 0 < high, got {clamp}")
        self.spec = spec
        self.l_free = float(l_free)
        self.l_occ = float(l_occ)
        self.clamp = (float(clamp[0]), float(clamp[1]))
        self.logodds = np.zeros(spec.shape, np.float32)

    @property
    def logodds(self) -> NDArray[np.float32]:
        """The log-odds grid (float32, ``spec.shape``); setting it forgets :attr:`top` and
        :attr:`floor_frames`."""
        return self._logodds

    @logodds.setter
    def logodds(self, value: NDArray[np.float32]) -> None:
        self._logodds = value
        self.top = np.zeros(self.spec.shape, np.float32)
        self.floor_frames = np.zeros(self.spec.shape, np.uint16)

    @classmethod
    def from_prior(
        cls,
        spec: GridSpec,
        prior_logodds: ArrayLike,
        l_free: float = OccupancyConfig.l_free,
        l_occ: float = OccupancyConfig.l_occ,
        clamp: tuple[float, float] = OccupancyConfig.clamp,
    ) -> LogOddsMap:
        """A map starting from a prior log-odds grid of shape ``spec.shape`` (clamped)."""
        prior = np.asarray(prior_logodds, np.float32)
        if prior.shape != spec.shape:
            raise ValueError(f"prior shape {prior.shape} does not match grid shape {spec.shape}")
        m = cls(spec, l_free, l_occ, clamp)
        m.logodds = np.clip(prior, *m.clamp).astype(np.float32)
        return m

    def copy(self) -> LogOddsMap:
        m = LogOddsMap(self.spec, self.l_free, self.l_occ, self.clamp)
        m.logodds = self.logodds.copy()
        m.top, m.floor_frames = self.top.copy(), self.floor_frames.copy()
        return m

    def update(
        self,
        points_w: ArrayLike,
        z_ground: float,
        camera_height: float,
        camera_xy: ArrayLike | None = None,
        free_tol: float = FLOOR_TOLERANCE,
        obstacle_min: float = OBSTACLE_MIN,
        *,
        clear_height: float | None = None,
        min_cell_points: int = 1,
        max_obstacle_range: float | None = None,
        protect_free: bool = False,
    ) -> PointClasses:
        """Fuse one frame of metric world points (N, 3); returns their classes.

        The keyword options (defaults: the plain fusion of the class docstring) are
        :class:`OccupancyConfig`'s: with ``clear_height`` and ``camera_xy`` the free evidence runs
        along every point's sight line from the camera (at ``camera_height`` above the ground) where
        it is at most ``clear_height`` m high (:func:`_sight_line_cells`) instead of the 2D rays to
        obstacle cells, and in a cell with obstacle points fused (:attr:`top`) only where it runs
        below the highest of them: a line over a low box proves nothing about the box; obstacle
        cells need ``min_cell_points`` points and, with ``camera_xy``, to lie within
        ``max_obstacle_range`` m of it; ``protect_free``: a cell below 0 (seen free) rises to 0 at
        most in this frame.
        """
        P = np.asarray(points_w, float).reshape(-1, 3)
        classes = classify_points(P, z_ground, camera_height, free_tol, obstacle_min)
        W = self.spec.shape[1]
        obstacle = P[classes.obstacle]
        if camera_xy is not None and max_obstacle_range is not None:
            near = np.linalg.norm(obstacle[:, :2] - np.asarray(camera_xy, float)[:2], axis=1)
            obstacle = obstacle[near <= max_obstacle_range]
        occ = _unique_cells(self.spec, obstacle[:, :2], min_cell_points)
        free = [_unique_cells(self.spec, P[classes.free, :2])]
        floor = self.floor_frames.reshape(-1)
        floor[free[0]] = np.minimum(floor[free[0]], np.iinfo(np.uint16).max - 1) + 1
        if camera_xy is not None and clear_height is not None:
            seen = P[classes.free | classes.obstacle] - [0.0, 0.0, z_ground]
            seen[:, 2] = np.maximum(seen[:, 2], 0.0)
            lines, line_z = _sight_line_cells(self.spec, camera_xy, camera_height, seen, clear_height)
            top = self.top.reshape(-1)[lines]
            free.append(lines[(top == 0.0) | (line_z < top)])
            self._raise_top(obstacle, z_ground, occ)
        elif camera_xy is not None and len(occ):
            start = self.spec.world_to_cell(np.asarray(camera_xy, float)[:2])
            ends = _farthest_per_direction(start, np.stack([occ // W, occ % W], axis=1))
            ray = _ray_cells(start, ends)
            ray = ray[self.spec.contains(ray)]
            free.append(np.unique(ray[:, 0] * W + ray[:, 1]))
        free_cells = np.setdiff1d(np.concatenate(free), occ, assume_unique=False)
        flat = self.logodds.reshape(-1)
        if protect_free:
            before = flat[occ]
            flat[occ] = np.where(before < 0.0, np.minimum(before + self.l_occ, 0.0), before + self.l_occ)
        else:
            flat[occ] += self.l_occ
        flat[free_cells] += self.l_free
        np.clip(self.logodds, *self.clamp, out=self.logodds)
        return classes

    def _raise_top(self, obstacle: NDArray[np.float64], z_ground: float, occ: NDArray[np.int64]) -> None:
        """Raise :attr:`top` of the obstacle cells ``occ`` (flat) to their highest obstacle point."""
        cells = self.spec.world_to_cell(obstacle[:, :2])
        inside = self.spec.contains(cells)
        flat = cells[inside, 0] * self.spec.shape[1] + cells[inside, 1]
        z = obstacle[inside, 2] - z_ground
        counted = np.isin(flat, occ)
        np.maximum.at(self.top.reshape(-1), flat[counted], z[counted].astype(np.float32))

    def mark_contact(
        self, pose: ArrayLike, radius: float, half_width: float | None = None, depth: float | None = None
    ) -> None:
        """Mark what a blocked forward step felt: the cells of a band across the heading, the centres
        of its nearest cells half a cell beyond ``radius`` m ahead of the robot's centre and of its
        farthest ``depth`` m farther (default 0: one cell deep; an egocentric crop's coarser
        ``resolution`` makes the band a cell deeper than the crop's pixels, so that their
        nearest-cell sampling cannot step over it), ``half_width`` m (default: half the radius) to
        each side, set to the clamp's upper bound. ``pose``: the robot's (x, y, yaw) in W (m, rad).
        Frames that later see those cells free lower them as any other cell's evidence.
        """
        x, y, yaw = np.asarray(pose, float)
        res = self.spec.resolution
        half = 0.5 * radius if half_width is None else float(half_width)
        deep = 0.0 if depth is None else max(0.0, float(depth))  # between the outer cells' centres
        lateral = np.linspace(-half, half, 2 * int(np.ceil(half / (0.5 * res))) + 1)
        ahead = radius + 0.5 * res + np.linspace(0.0, deep, int(np.ceil(deep / (0.5 * res))) + 1)
        heading, left = np.array([np.cos(yaw), np.sin(yaw)]), np.array([-np.sin(yaw), np.cos(yaw)])
        band = ahead[:, None, None] * heading + lateral[None, :, None] * left
        cells = self.spec.world_to_cell(np.array([x, y]) + band.reshape(-1, 2))
        cells = cells[self.spec.contains(cells)]
        self.logodds[cells[:, 0], cells[:, 1]] = self.clamp[1]

    def probability(self) -> NDArray[np.float32]:
        """Occupancy probability per cell, 0.5 where unknown."""
        return (1.0 / (1.0 + np.exp(-self.logodds))).astype(np.float32)

    def occupied(self, threshold: float = 0.65) -> NDArray[np.bool_]:
        return self.probability() > threshold

    def free(self, threshold: float = 0.35) -> NDArray[np.bool_]:
        return self.probability() < threshold

    def floor_seen(self, threshold: float = 0.35, min_frames: int = 2) -> NDArray[np.bool_]:
        """Cells :meth:`free` below ``threshold`` whose floor was seen in ``min_frames`` frames:
        free by what the camera saw there, not only by sight lines passing over (which a low
        obstacle in the camera's blind zone below its view lets through)."""
        return self.free(threshold) & (self.floor_frames >= min_frames)

    def egocentric_crop(
        self,
        x: float,
        y: float,
        yaw: float,
        size_cells: int,
        resolution: float | None = None,
        occupied_threshold: float = 0.65,
        free_threshold: float = 0.35,
    ) -> NDArray[np.uint8]:
        """(size, size) uint8 crop centred on the robot at (x, y) facing up.

        Row 0 is ahead of the robot (heading ``yaw``, counter-clockwise from +x), column
        index grows to the robot's right. Pixels are ``resolution`` metres (default: the
        map's) and encode ``OCCUPIED`` (255) / ``FREE`` (128) / ``UNKNOWN`` (0, also outside
        the map), nearest-cell sampled.
        """
        if size_cells < 1:
            raise ValueError(f"size_cells must be >= 1, got {size_cells}")
        res = self.spec.resolution if resolution is None else float(resolution)
        labels = np.full(self.spec.shape, UNKNOWN, np.uint8)
        p = self.probability()
        labels[p < free_threshold] = FREE
        labels[p > occupied_threshold] = OCCUPIED
        centre = (size_cells - 1) / 2.0
        r, c = np.meshgrid(np.arange(size_cells), np.arange(size_cells), indexing="ij")
        ahead = (centre - r) * res
        right = (c - centre) * res
        wx = x + ahead * np.cos(yaw) + right * np.sin(yaw)
        wy = y + ahead * np.sin(yaw) - right * np.cos(yaw)
        col = (wx - self.spec.origin[0]) / self.spec.resolution - 0.5
        row = (wy - self.spec.origin[1]) / self.spec.resolution - 0.5
        return map_coordinates(labels, [row, col], order=0, mode="constant", cval=UNKNOWN).astype(np.uint8)
