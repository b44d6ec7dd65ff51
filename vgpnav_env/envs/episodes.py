"""Point-goal episodes: deterministic start/goal sampling and geodesic distance look-ups.

Episodes follow Habitat's point-goal generator: start and goal on navigable cells of one connected
component, geodesic distance within [``min_geodesic``, ``max_geodesic``] metres, and near-straight
pairs (geodesic / Euclidean < ``straight_ratio``) rejected with probability
``straight_reject_prob`` so that most episodes need turns. The start yaw is uniform.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import distance_transform_edt

from vgpnav_env.grid import GridSpec, geodesic_distance


@dataclass(frozen=True)
class Episode:
    """Start pose (x, y, yaw) and goal (x, y) in W; ``geodesic`` = shortest path length (metres)."""

    start: tuple[float, float, float]
    goal: tuple[float, float]
    geodesic: float


class GeodesicField:
    """Geodesic distance (metres) to ``goal_xy`` over ``traversable`` cells, at any world point.

    Points off the traversable cells (e.g. hugging a wall closer than the erosion margin) get the
    distance of the nearest reachable cell plus the straight distance to its centre.
    """

    def __init__(self, traversable: NDArray[np.bool_], spec: GridSpec, goal_xy: ArrayLike) -> None:
        self.spec = spec
        self.goal = np.asarray(goal_xy, float)[:2]
        self.distance = np.asarray(geodesic_distance(traversable, spec, self.goal), float)
        finite = np.isfinite(self.distance)
        if not finite.any():
            raise ValueError(f"goal {tuple(self.goal)} is not reachable on the traversable grid")
        self._nearest = distance_transform_edt(~finite, return_distances=False, return_indices=True)

    def __call__(self, xy: ArrayLike) -> float:
        xy = np.asarray(xy, float)[:2]
        rows, cols = self.spec.shape
        r, c = self.spec.world_to_cell(xy)
        r, c = int(np.clip(r, 0, rows - 1)), int(np.clip(c, 0, cols - 1))
        d = self.distance[r, c]
        if np.isfinite(d):
            return float(d)
        nr, nc = int(self._nearest[0, r, c]), int(self._nearest[1, r, c])
        centre = self.spec.cell_to_world(np.array([nr, nc]))
        return float(self.distance[nr, nc] + np.linalg.norm(xy - centre))


def sample_episode(
    navigable: NDArray[np.bool_],
    spec: GridSpec,
    rng: np.random.Generator,
    *,
    min_geodesic: float = 1.0,
    max_geodesic: float = 10.0,
    straight_ratio: float = 1.1,
    straight_reject_prob: float = 0.98,
    is_valid: Callable[[NDArray[np.float64]], bool] | None = None,
    max_starts: int = 50,
    goals_per_start: int = 200,
) -> Episode:
    """Sample a start/goal pair on ``navigable`` (one connected component) with ``rng``.

    ``is_valid(pose)`` may reject start poses or goal points (e.g. where the robot hull would
    touch collision geometry); it receives (x, y, yaw). Raises ``RuntimeError`` if no episode
    satisfies the constraints after ``max_starts`` start cells.
    """
    if not 0.0 < min_geodesic <= max_geodesic:
        raise ValueError(f"need 0 < min_geodesic <= max_geodesic, got {min_geodesic}, {max_geodesic}")
    cells = np.argwhere(navigable)
    if len(cells) == 0:
        raise ValueError("no navigable cells to sample episodes from")
    centres = spec.cell_to_world(cells)
    for _ in range(max_starts):
        start_xy = centres[rng.integers(len(cells))]
        yaw = float(rng.uniform(-np.pi, np.pi))
        start = np.array([start_xy[0], start_xy[1], yaw])
        if is_valid is not None and not is_valid(start):
            continue
        d = np.asarray(geodesic_distance(navigable, spec, start_xy), float)[cells[:, 0], cells[:, 1]]
        candidates = np.flatnonzero(np.isfinite(d) & (d >= min_geodesic) & (d <= max_geodesic))
        if len(candidates) == 0:
            continue
        for _ in range(goals_per_start):
            i = candidates[rng.integers(len(candidates))]
            euclid = float(np.linalg.norm(centres[i] - start_xy))
            if d[i] / max(euclid, 1e-9) < straight_ratio and rng.random() < straight_reject_prob:
                continue
            goal = centres[i]
            if is_valid is not None and not is_valid(np.array([goal[0], goal[1], 0.0])):
                continue
            return Episode(
                start=(float(start[0]), float(start[1]), yaw),
                goal=(float(goal[0]), float(goal[1])),
                geodesic=float(d[i]),
            )
    raise RuntimeError(
        f"could not sample an episode with geodesic distance in [{min_geodesic}, {max_geodesic}] m "
        f"after {max_starts} start cells; is the navigable area too small?"
    )
