"""Coverage trajectories over a navigable grid: the camera paths of database and query runs.

A coverage trajectory visits one *cover point* per ``cover_spacing`` x ``cover_spacing`` block of
the largest navigable component (so every navigable cell lies within ``sqrt(2) * cover_spacing`` of
a visited point), in a greedy nearest-unvisited tour whose legs are geodesic grid paths shortened
by line-of-sight. Frames are placed every ``spacing`` metres of travel, on turns (heading changes
larger than ``max_turn_deg`` get intermediate in-place frames) and on occasional in-place
look-around turns, so the frames see the scene from several headings. Poses are OpenCV ``T_wc``
(see :func:`vgpnav_env.geometry.camera_pose`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from skimage.draw import line as draw_line
from skimage.graph import MCP_Geometric

from vgpnav_env import grid
from vgpnav_env.geometry import camera_pose, wrap_angle
from vgpnav_env.grid import GridSpec, largest_component
from vgpnav_env.robot import CAMERA_HEIGHT

#: Bumped whenever the planner's output for given arguments changes (invalidates cached builds).
TRAJECTORY_VERSION = 2
#: Camera height (mean, half-range) in metres and downward pitch range in degrees, per DESIGN.md
#: (queries: the robot's camera height).
DATABASE_HEIGHT = (1.5, 0.1)
QUERY_HEIGHT = (CAMERA_HEIGHT, 0.05)
PITCH_RANGE_DEG = (15.0, 30.0)
#: Paths and cover points prefer cells at least this far (metres) inside the navigable area.
CLEARANCE_CAP = 0.5
#: Extra travel cost per metre on the navigable boundary (linearly less up to ``CLEARANCE_CAP``).
WALL_COST = 2.0


@dataclass(frozen=True)
class _Waypoint:
    """A polyline vertex (world xy) and whether the camera looks around there."""

    xy: NDArray[np.float64]
    look_around: bool = False


def _wall_penalty(clearance: NDArray[np.float64]) -> NDArray[np.float64]:
    """0 at ``CLEARANCE_CAP`` or more from the navigable boundary, rising to 1 at the boundary."""
    return 1.0 - np.minimum(clearance, CLEARANCE_CAP) / CLEARANCE_CAP


def cover_cells(component: NDArray[np.bool_], spec: GridSpec, cover_spacing: float) -> NDArray[np.int64]:
    """One (row, col) per ``cover_spacing`` block holding component cells, shape (M, 2), ordered
    row-major by block: the cell minimising distance to the block's centre + a penalty for
    standing near the navigable boundary (so cameras keep away from walls and furniture)."""
    block = max(1, int(round(cover_spacing / spec.resolution)))
    rows, cols = np.nonzero(component)
    block_id = np.stack([rows // block, cols // block], axis=1)
    centre = (block_id + 0.5) * block - 0.5
    score = np.hypot(rows - centre[:, 0], cols - centre[:, 1]) * spec.resolution
    score += cover_spacing * _wall_penalty(grid.clearance(component, spec)[rows, cols])
    order = np.lexsort((score, block_id[:, 1], block_id[:, 0]))
    keys = block_id[order]
    first = np.ones(len(order), bool)
    first[1:] = np.any(keys[1:] != keys[:-1], axis=1)
    chosen = order[first]
    return np.stack([rows[chosen], cols[chosen]], axis=1).astype(np.int64)


def _line_clear(
    clearance: NDArray[np.float64], a: NDArray[np.int64], b: NDArray[np.int64], need: float
) -> bool:
    rr, cc = draw_line(int(a[0]), int(a[1]), int(b[0]), int(b[1]))
    return bool(np.all(clearance[rr, cc] >= need))


def _shortcut(clearance: NDArray[np.float64], cells: NDArray[np.int64]) -> NDArray[np.int64]:
    """Vertices of a grid path after greedy line-of-sight shortening (first and last kept); a
    shortcut may not pass closer to the boundary than the path it replaces (capped)."""
    path_clear = np.minimum(clearance[cells[:, 0], cells[:, 1]], CLEARANCE_CAP)
    keep = [0]
    i = 0
    while i < len(cells) - 1:
        j = i + 1
        need = min(path_clear[i], path_clear[j])
        while j + 1 < len(cells):
            need_next = min(need, path_clear[j + 1])
            if not _line_clear(clearance, cells[i], cells[j + 1], need_next - 1e-9):
                break
            j, need = j + 1, need_next
        keep.append(j)
        i = j
    return cells[keep]


def _two_opt(D: NDArray[np.float64], order: list[int]) -> list[int]:
    """Improve an open path over the distance matrix ``D`` by segment reversals until none helps."""
    order = list(order)
    improved = True
    while improved:
        improved = False
        for i in range(1, len(order) - 1):
            o = np.asarray(order)
            a, b = o[i - 1], o[i]
            js = np.arange(i + 1, len(o))
            nxt = np.append(o[js[:-1] + 1], -1)
            gain = D[a, b] - D[a, o[js]]
            closed = nxt >= 0
            gain[closed] += D[o[js[closed]], nxt[closed]] - D[b, nxt[closed]]
            k = int(np.argmax(gain))
            if gain[k] > 1e-6:
                j = int(js[k])
                order[i : j + 1] = order[i : j + 1][::-1]
                improved = True
    return order


def _tour(
    component: NDArray[np.bool_],
    spec: GridSpec,
    covers: NDArray[np.int64],
    rng: np.random.Generator,
    p_look: float,
) -> list[_Waypoint]:
    """Short geodesic tour over the cover cells (nearest neighbour + 2-opt), as polyline waypoints."""
    clearance = grid.clearance(component, spec)
    # Travel costs up to 1 + WALL_COST near the navigable boundary: paths keep to open space.
    mcp = MCP_Geometric(np.where(component, 1.0 + WALL_COST * _wall_penalty(clearance), np.inf))
    D = np.stack([mcp.find_costs([tuple(c)])[0][covers[:, 0], covers[:, 1]] for c in covers])
    order = [int(rng.integers(len(covers)))]
    left = np.ones(len(covers), bool)
    left[order[0]] = False
    while left.any():
        d = np.where(left, D[order[-1]], np.inf)
        order.append(int(np.argmin(d)))
        left[order[-1]] = False
    order = _two_opt(D, order)
    looks = rng.random(len(order)) < p_look
    waypoints = [_Waypoint(spec.cell_to_world(covers[order[0]]), bool(looks[0]))]
    for k in range(1, len(order)):
        goal = tuple(covers[order[k]])
        mcp.find_costs([tuple(covers[order[k - 1]])], [goal])
        path = np.asarray(mcp.traceback(goal), np.int64)
        for cell in _shortcut(clearance, path)[1:-1]:
            waypoints.append(_Waypoint(spec.cell_to_world(cell)))
        waypoints.append(_Waypoint(spec.cell_to_world(covers[order[k]]), bool(looks[k])))
    return waypoints


def _turn_yaws(start: float, delta: float, max_turn: float) -> list[float]:
    """Intermediate headings for an in-place turn by ``delta`` (exclusive of both ends)."""
    n = int(np.ceil(abs(delta) / max_turn))
    return [start + delta * k / n for k in range(1, n)]


def _frames_along(
    waypoints: list[_Waypoint], spacing: float, max_turn: float, look_step: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Frame positions (N, 2) and headings (N,) along the waypoint polyline."""
    keep = [0] + [
        i for i in range(1, len(waypoints)) if np.linalg.norm(waypoints[i].xy - waypoints[i - 1].xy) > 1e-9
    ]
    wps = [waypoints[i] for i in keep]  # no zero-length segments: every segment has a heading
    n_look = int(round(2 * np.pi / look_step))
    if len(wps) == 1:
        return np.repeat(wps[0].xy[None], n_look, axis=0), np.arange(n_look) * look_step
    xy: list[NDArray[np.float64]] = [wps[0].xy]
    yaw: list[float] = [float(np.arctan2(*(wps[1].xy - wps[0].xy)[::-1]))]
    carry = spacing  # arc length into the current segment where the next travel frame goes
    for i in range(len(wps) - 1):
        a, b = wps[i].xy, wps[i + 1].xy
        h = float(np.arctan2(*(b - a)[::-1]))
        turns: list[float] = []
        if i > 0 and wps[i].look_around:
            turns = [yaw[-1] + look_step * k for k in range(1, n_look + 1)]
        start = turns[-1] if turns else yaw[-1]
        delta = float(wrap_angle(h - start))
        if abs(delta) > max_turn:
            turns += _turn_yaws(start, delta, max_turn) + [h]
        if turns:
            xy.extend([a] * len(turns))
            yaw.extend(turns)
            carry = spacing
        length = float(np.linalg.norm(b - a))
        s = carry
        while s < length - 1e-9:
            xy.append(a + (b - a) * (s / length))
            yaw.append(h)
            s += spacing
        carry = s - length
    return np.asarray(xy), np.asarray(yaw)


def coverage_trajectory(
    navigable: NDArray[np.bool_],
    spec: GridSpec,
    rng: np.random.Generator | int,
    *,
    spacing: float = 0.3,
    height: tuple[float, float] = DATABASE_HEIGHT,
    pitch_deg: tuple[float, float] = PITCH_RANGE_DEG,
    cover_spacing: float = 2.0,
    max_turn_deg: float = 45.0,
    look_around_prob: float = 0.2,
    look_around_step_deg: float = 60.0,
    yaw_jitter_deg: float = 10.0,
) -> NDArray[np.float64]:
    """Camera poses ``T_wc`` (N, 4, 4) of a path covering the largest navigable component.

    ``navigable`` is a boolean grid over ``spec`` (True = the camera's robot may stand there).
    Frames come every ``spacing`` metres of travel and on turns (no in-place step exceeds
    ``max_turn_deg``); at each visited cover point, with probability ``look_around_prob``, the
    camera turns a full circle in ``look_around_step_deg`` steps. Heading = direction of travel
    + uniform jitter of +-``yaw_jitter_deg``; height = ``height[0]`` +- ``height[1]`` (metres,
    uniform per frame); pitch uniform in ``pitch_deg`` (degrees down). Deterministic per seed.
    """
    navigable = np.asarray(navigable, bool)
    if navigable.shape != tuple(spec.shape):
        raise ValueError(f"navigable grid shape {navigable.shape} does not match grid spec {spec.shape}")
    if spacing <= 0 or cover_spacing <= 0:
        raise ValueError(f"spacing and cover_spacing must be positive metres, got {spacing}, {cover_spacing}")
    if not 0 < max_turn_deg <= 180 or not 0 < look_around_step_deg <= 180:
        raise ValueError("max_turn_deg and look_around_step_deg must lie in (0, 180]")
    if height[1] < 0 or height[0] - height[1] <= 0:
        raise ValueError(f"height must be (mean, half-range) with a positive minimum, got {height}")
    if not 0 <= pitch_deg[0] <= pitch_deg[1] < 90:
        raise ValueError(f"pitch_deg must be (low, high) with 0 <= low <= high < 90, got {pitch_deg}")
    rng = np.random.default_rng(rng)
    component = largest_component(navigable)
    if not component.any():
        raise ValueError("navigable grid has no navigable cell: cannot plan a coverage trajectory")
    covers = cover_cells(component, spec, cover_spacing)
    waypoints = _tour(component, spec, covers, rng, look_around_prob)
    xy, yaw = _frames_along(waypoints, spacing, np.deg2rad(max_turn_deg), np.deg2rad(look_around_step_deg))
    n = len(xy)
    yaw = yaw + rng.uniform(-1.0, 1.0, n) * np.deg2rad(yaw_jitter_deg)
    z = height[0] + rng.uniform(-1.0, 1.0, n) * height[1]
    pitch = np.deg2rad(rng.uniform(pitch_deg[0], pitch_deg[1], n))
    frames = zip(xy, z, yaw, pitch, strict=True)
    return np.stack([camera_pose((x, y, h), float(wrap_angle(a)), p) for (x, y), h, a, p in frames])
