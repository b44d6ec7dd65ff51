"""Map quality: a fused obstacle map scored against the true occupancy of the layout the robot is in.

Every grid here is a boolean ``(rows, cols)`` array over one :class:`~vgpnav_env.grid.GridSpec`
(the fused map's). ``truth``: the ground-truth obstacle cells of the robot's layout rasterised onto
that spec (:func:`truth_on`); ``observed``: the cells the robot's camera saw, i.e. the cells of the
true visible surface below the robot height within ``max_depth`` of the camera, accumulated over the
frames (:func:`visible_cells`); ``occupied``: the map's occupied cells.

Scores (:func:`map_score`) are over the observed cells, with a tolerance of ``tolerance`` cells
(Chebyshev distance; default 1, one map cell, so that a wall face landing in the cell in front of
the wall's cells is not both a phantom and a miss): a predicted occupied cell is right when a true
obstacle lies within the tolerance, a true obstacle cell is found when a predicted one does.
precision = right / predicted, recall = found / true, IoU = 1 / (1/precision + 1/recall - 1)
(the cell IoU when ``tolerance`` is 0). *Phantoms* are predicted occupied cells with no true
obstacle within the tolerance; :func:`path_phantoms` counts those in the corridor of the true
shortest path (cells within the robot radius of it), the ones that push a plan off it.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import binary_dilation, distance_transform_edt

from vgpnav_env.geometry import PinholeCamera, transform_points
from vgpnav_env.grid import GridSpec

if TYPE_CHECKING:
    from vgpnav_env.groundtruth import GroundTruthMap

#: Default tolerance of the scores (cells, Chebyshev) and the observed range (m, the perception's).
TOLERANCE_CELLS = 1
MAX_DEPTH_M = 5.0


@dataclass(frozen=True)
class MapScore:
    """Occupied precision, recall and IoU over the observed cells (None when undefined: no
    predicted, or no true, occupied cell observed) and the counts behind them."""

    precision: float | None
    recall: float | None
    iou: float | None
    predicted: int
    truth: int
    phantoms: int
    misses: int


def rasterize(spec: GridSpec, xy: ArrayLike) -> NDArray[np.bool_]:
    """Cells of ``spec`` hit by world points (N, 2) (points off the grid are dropped)."""
    out = np.zeros(spec.shape, bool)
    cells = spec.world_to_cell(np.asarray(xy, float).reshape(-1, 2))
    cells = cells[spec.contains(cells)]
    out[cells[:, 0], cells[:, 1]] = True
    return out


def truth_on(spec: GridSpec, gt: GroundTruthMap) -> NDArray[np.bool_]:
    """The ground-truth obstacle cells on ``spec``: the same array when the grids coincide, else the
    cells of ``spec`` holding a ground-truth obstacle cell's centre (or containing its nearest)."""
    if gt.spec == spec:
        return gt.obstacle.copy()
    out = rasterize(spec, gt.spec.cell_to_world(np.argwhere(gt.obstacle)))
    if spec.resolution < gt.spec.resolution:  # a finer grid: every cell whose centre lies in one
        cells = gt.spec.world_to_cell(spec.centres())
        inside = gt.spec.contains(cells)
        out[inside] |= gt.obstacle[cells[inside][:, 0], cells[inside][:, 1]]
    return out


def visible_cells(
    spec: GridSpec,
    camera: PinholeCamera,
    T_wc: ArrayLike,
    depth: ArrayLike,
    max_height: float,
    max_depth: float = MAX_DEPTH_M,
    stride: int = 4,
) -> NDArray[np.bool_]:
    """Cells of the true visible surface in one frame: every ``stride``-th pixel of the true z-depth
    (H, W) within ``max_depth`` m, back-projected from the true camera pose ``T_wc``, at most
    ``max_height`` m above the floor (z = 0)."""
    rays = camera.rays()[::stride, ::stride]
    d = np.asarray(depth, float)[::stride, ::stride]
    keep = np.isfinite(d) & (d > 0) & (d <= max_depth)
    points = transform_points(T_wc, rays[keep] * d[keep][:, None])
    return rasterize(spec, points[points[:, 2] <= max_height, :2])


def _near(mask: NDArray[np.bool_], tolerance: int) -> NDArray[np.bool_]:
    if tolerance <= 0:
        return mask
    return binary_dilation(mask, np.ones((3, 3), bool), iterations=tolerance)


def map_score(
    occupied: ArrayLike,
    truth: ArrayLike,
    observed: ArrayLike,
    tolerance: int = TOLERANCE_CELLS,
) -> MapScore:
    """Occupied precision, recall and IoU of ``occupied`` against ``truth`` over ``observed`` (module
    docstring); ``phantoms`` / ``misses``: observed predicted cells with no true obstacle near /
    observed true cells with no predicted one near."""
    occupied, truth, observed = (np.asarray(a, bool) for a in (occupied, truth, observed))
    predicted = occupied & observed
    true = truth & observed
    right = int((predicted & _near(truth, tolerance)).sum())
    found = int((true & _near(occupied, tolerance)).sum())
    n_pred, n_true = int(predicted.sum()), int(true.sum())
    precision = right / n_pred if n_pred else None
    recall = found / n_true if n_true else None
    iou = None
    if precision is not None and recall is not None:
        iou = 0.0 if precision == 0 or recall == 0 else 1.0 / (1.0 / precision + 1.0 / recall - 1.0)
    return MapScore(precision, recall, iou, n_pred, n_true, n_pred - right, n_true - found)


def phantom_cells(
    occupied: ArrayLike, truth: ArrayLike, tolerance: int = TOLERANCE_CELLS
) -> NDArray[np.bool_]:
    """Occupied cells with no true obstacle within ``tolerance`` cells (observed or not)."""
    return np.asarray(occupied, bool) & ~_near(np.asarray(truth, bool), tolerance)


def corridor(spec: GridSpec, path: ArrayLike | None, radius: float) -> NDArray[np.bool_]:
    """Cells whose centre lies within ``radius`` m of a polyline ``path`` (N, 2) of world xy (all
    False without a path)."""
    if path is None or len(path) == 0:
        return np.zeros(spec.shape, bool)
    path = np.asarray(path, float)
    pieces = [path[:1]]
    for a, b in zip(path[:-1], path[1:], strict=True):
        n = max(1, int(np.ceil(2.0 * np.linalg.norm(b - a) / spec.resolution)))
        pieces.append(a + np.linspace(0.0, 1.0, n + 1)[1:, None] * (b - a))
    on = rasterize(spec, np.concatenate(pieces))
    return distance_transform_edt(~on) * spec.resolution <= radius


def path_phantoms(
    occupied: ArrayLike, truth: ArrayLike, path_corridor: ArrayLike, tolerance: int = TOLERANCE_CELLS
) -> int:
    """Phantom cells (:func:`phantom_cells`) inside ``path_corridor`` (observed or not: a plan meets
    them either way, e.g. a prior's obstacle the layout no longer has)."""
    return int((phantom_cells(occupied, truth, tolerance) & np.asarray(path_corridor, bool)).sum())


@dataclass(frozen=True)
class MapState:
    """What the ``"map"`` measures (:mod:`vgpnav_env.measures`) read after a frame: the map's
    ``occupied`` cells, the ``truth`` on the same spec, the ``observed`` cells so far, the true
    shortest path's ``path_corridor`` and the score ``tolerance`` (cells)."""

    occupied: NDArray[np.bool_]
    truth: NDArray[np.bool_]
    observed: NDArray[np.bool_]
    path_corridor: NDArray[np.bool_]
    tolerance: int = TOLERANCE_CELLS

    @cached_property
    def score(self) -> MapScore:
        """:func:`map_score` of this frame (computed once for all its measures)."""
        return map_score(self.occupied, self.truth, self.observed, self.tolerance)

    @property
    def path_phantoms(self) -> int:
        return path_phantoms(self.occupied, self.truth, self.path_corridor, self.tolerance)


class MapTracker:
    """The observed cells of one episode of a point-goal env (``env.unwrapped``: ground truth,
    navigable cells, camera, robot radius and height), as :class:`MapState` per frame.

    ``start(spec, info)`` at every reset (``info``: the env's, with the true ``T_wc``, ``depth``,
    ``start`` and ``goal``) sets the truth on the fused map's ``spec`` and the corridor of the true
    shortest path; ``observe(occupied, info)`` adds the frame's visible cells (when ``info`` has a
    depth; else ``depth_fn()`` renders it, e.g. for envs made without images).
    """

    def __init__(self, env, tolerance: int = TOLERANCE_CELLS, max_depth: float = MAX_DEPTH_M) -> None:
        self.env = env.unwrapped
        self.tolerance, self.max_depth = int(tolerance), float(max_depth)
        self.spec: GridSpec | None = None
        self.truth = self.observed = self.path_corridor = np.zeros((0, 0), bool)

    def start(self, spec: GridSpec, info: dict) -> None:
        from vgpnav_env.grid import shortest_path

        base = self.env
        gt = base.ground_truth
        if spec != self.spec:
            self.spec, self.truth = spec, truth_on(spec, gt)
        try:
            path = shortest_path(base.world.navigable, gt.spec, np.asarray(info["start"])[:2], info["goal"])
        except ValueError:
            path = None
        self.path_corridor = corridor(spec, path, base.robot_radius)
        self.observed = np.zeros(spec.shape, bool)

    def observe(self, occupied: NDArray[np.bool_], info: dict) -> MapState:
        base = self.env
        depth = info.get("depth")
        if depth is None:
            depth = base.render_depth()
        self.observed |= visible_cells(
            self.spec, base.camera, info["T_wc"], depth, base.ground_truth.robot_height, self.max_depth
        )
        return MapState(np.asarray(occupied, bool), self.truth, self.observed.copy(), self.path_corridor,
                        self.tolerance)  # fmt: skip
