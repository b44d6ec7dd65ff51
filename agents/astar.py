"""A* waypoint-following agent over an occupancy map, with the env's discrete actions.

The agent plans on a 2D obstacle grid (``True`` = obstacle; free and unknown cells are both
traversable: optimistic planning) inflated by the robot radius, from a pose estimate
(x, y, yaw) to a goal (x, y), all in W (metres, radians). It turns toward a waypoint about
``lookahead`` metres ahead on the path (the farthest one in a straight traversable line, else the
path point ``min_waypoint`` metres ahead along the path) when the heading error exceeds half a
turn step -- ``reverse_turn`` turn steps to undo its last turn while two steps ahead are clear
(hysteresis: with 15 degree turns a path between two headings otherwise makes it zigzag left,
forward, right, forward) -- and
otherwise drives forward; it stops when the (estimated) goal distance is below ``goal_radius``.
It replans when the goal (by more than half a cell: a goal rebuilt from an
observation's float32 distance and bearing jitters by micrometres) or the grid changes, when the
map changes so that the rest of the path is
no longer traversable (or ``replan_every`` steps after the last plan), when it strays from the
path, and when a forward action was blocked (its bump sensor, else no progress of the pose; it then
marks contact points ahead as obstacles, except where its body stood: a contact point its body
covered, or whose cell the map has since seen free on consecutive frames some time after the bump,
is forgotten).

The plan is the cheapest path on a costmap, as ROS nav2's inflation layer: cells within the
inflation radius (robot radius + margin) of an obstacle are lethal, and beyond it a cell costs
``1 + cost_weight * exp(-(clearance - inflation) / cost_decay)`` per metre, so the path keeps to the
middle of doorways and passages instead of grazing their edges (its smoothing never takes a
shortcut nearer to obstacles than the plan went). Mapped cells within the robot radius of the goal
are ignored (the task puts goals where the robot fits). It stops only when the goal lies within
``success_radius`` with the estimate's uncertainty (``distance + stop_z * sigma``, sigma the
position standard deviation it is given); too unsure at the end of its path, it turns in place for
a better fix (one full turn at most). Recovery (nav2's spin): ``recovery_bumps`` bumps within
``recovery_window`` decisions make it turn once in full in place, so the camera maps what it keeps
bumping into, before it plans again.
"""

from __future__ import annotations

import logging
from collections import deque

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import distance_transform_edt

from vgpnav_env.geometry import wrap_angle
from vgpnav_env.grid import GridSpec, line_of_sight, shortest_path
from vgpnav_env.robot import FORWARD_STEP, ROBOT_RADIUS, TURN_STEP_DEG, Action

logger = logging.getLogger(__name__)

#: A contact point is reopened where the fused map's occupancy probability is below this (about
#: four frames' net free evidence) and the floor there was seen
#: (:meth:`~vgpnav_env.perception.occupancy.LogOddsMap.floor_seen`): sight lines over a low
#: obstacle in the camera's blind zone reopened the contacts on it, and the robot bumped it again.
REOPEN_FREE = 0.2


def inflate(obstacles: NDArray[np.bool_], resolution: float, radius: float) -> NDArray[np.bool_]:
    """Cells whose centre lies within ``radius`` metres of an obstacle cell centre (or on one)."""
    if not obstacles.any():
        return np.zeros_like(obstacles, dtype=bool)
    return distance_transform_edt(~obstacles) * resolution <= radius


def _densify(path: NDArray[np.float64], spacing: float) -> NDArray[np.float64]:
    """Points every ``spacing`` metres along a polyline (N, 2), vertices included."""
    out = [path[:1]]
    for a, b in zip(path[:-1], path[1:], strict=True):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / spacing)))
        out.append(a + np.linspace(0.0, 1.0, n + 1)[1:, None] * (b - a))
    return np.concatenate(out)


class AStarAgent:
    """Plans with ``grid.shortest_path`` and follows the path with discrete actions."""

    def __init__(
        self,
        robot_radius: float = ROBOT_RADIUS,
        inflation_margin: float = 0.03,
        navigable: NDArray[np.bool_] | None = None,
        goal_radius: float = 0.35,
        blocked_goal_radius: float = 0.45,
        lookahead: float = 0.5,
        forward_step: float = FORWARD_STEP,
        turn_step_deg: float = TURN_STEP_DEG,
        min_progress: float = 0.4,
        off_path_distance: float = 0.5,
        reverse_turn: float = 0.9,
        min_waypoint: float = 0.3,
        replan_every: int = 10,
        contact_arc_deg: float = 45.0,
        contact_margin: float = 0.06,
        contact_memory: int = 50,
        cost_weight: float = 2.0,
        cost_decay: float = 0.1,
        success_radius: float = 0.5,
        stop_z: float = 1.64,
        contact_free_frames: int = 2,
        reopen_after: int = 50,
        recovery_bumps: int = 3,
        recovery_window: int = 20,
        max_recoveries: int = 3,
    ) -> None:
        if robot_radius <= 0 or goal_radius <= 0 or lookahead <= 0 or forward_step <= 0:
            raise ValueError("robot_radius, goal_radius, lookahead and forward_step must be positive metres")
        self.robot_radius = float(robot_radius)
        self.inflation = float(robot_radius + inflation_margin)
        self.navigable = None if navigable is None else np.asarray(navigable, bool)
        self.goal_radius = float(goal_radius)
        self.blocked_goal_radius = max(float(blocked_goal_radius), self.goal_radius)
        self.lookahead = float(lookahead)
        self.forward_step = float(forward_step)
        self.turn_step = float(np.radians(turn_step_deg))
        self.min_progress = float(min_progress)
        self.off_path_distance = float(off_path_distance)
        if not 0.5 <= reverse_turn < 1.0 or min_waypoint <= 0:
            raise ValueError(f"need reverse_turn in [0.5, 1) turn steps and min_waypoint > 0 m, got "
                             f"{reverse_turn}, {min_waypoint}")  # fmt: skip
        self.reverse_turn = float(reverse_turn)
        self.min_waypoint = float(min_waypoint)
        if replan_every < 1:
            raise ValueError(f"replan_every must be >= 1 step, got {replan_every}")
        self.replan_every = int(replan_every)
        # Bearings from the heading of the contact points a blocked forward step marks on the
        # robot's front: the contact lies somewhere on the front half (one point straight ahead let
        # it bump again beside, along a wall the map does not hold).
        self.contact_arc = np.radians(np.unique([-contact_arc_deg, 0.0, contact_arc_deg]))
        # A contact point the robot's body covered (its centre within the radius less
        # ``contact_margin`` m of pose noise), now or during the last ``contact_memory`` steps, was a
        # wrong guess of where the contact was.
        if not 0 <= contact_margin < robot_radius or contact_memory < 1:
            raise ValueError(f"need 0 <= contact_margin < robot_radius m and contact_memory >= 1 step, got "
                             f"{contact_margin}, {contact_memory}")  # fmt: skip
        self.contact_clearance = self.robot_radius - float(contact_margin)
        self.contact_memory = int(contact_memory)
        # Costmap (as ROS nav2's inflation layer): beyond the inflation radius a cell costs
        # 1 + cost_weight * exp(-(clearance - inflation) / cost_decay) per metre crossed.
        if cost_weight < 0 or cost_decay <= 0:
            raise ValueError(f"need cost_weight >= 0 and cost_decay > 0 m, got {cost_weight}, {cost_decay}")
        self.cost_weight, self.cost_decay = float(cost_weight), float(cost_decay)
        # Stop only where the goal is within success_radius with the estimate's uncertainty:
        # distance + stop_z * sigma <= success_radius (sigma: the position standard deviation).
        self.success_radius, self.stop_z = float(success_radius), float(stop_z)
        if contact_free_frames < 1 or recovery_bumps < 2 or recovery_window < recovery_bumps:
            raise ValueError("need contact_free_frames >= 1 and 2 <= recovery_bumps <= recovery_window")
        self.contact_free_frames = int(contact_free_frames)
        # Only contacts at least this many decisions old are reopened: a contact point that lands on
        # floor seen free in front of the wall it stands for (pose noise) kept being reopened and
        # bumped again, the same wall many times over.
        self.reopen_after = int(reopen_after)
        self.recovery_bumps, self.recovery_window = int(recovery_bumps), int(recovery_window)
        self.max_recoveries = int(max_recoveries)
        self.turns_per_circle = int(np.ceil(2.0 * np.pi / self.turn_step - 1e-9))
        self.reset()

    def reset(self) -> None:
        """Forget the path, the blocked cells and the last action (call at every episode start)."""
        self.path: NDArray[np.float64] | None = None
        self._dense: NDArray[np.float64] | None = None
        self._along: NDArray[np.float64] | None = None
        self._free: NDArray[np.bool_] | None = None
        self._spec: GridSpec | None = None
        # contact points (world x, y in m), each with its bump's number, whether straight ahead and
        # for how many consecutive decisions since the map has seen its cell free
        self._contacts: list[tuple[NDArray[np.float64], int, bool, int]] = []
        self._bumps = 0
        self._bump_decision: dict[int, int] = {}  # bump number -> the decision it happened at
        self._steps = 0
        self._bump_steps: deque[int] = deque(maxlen=self.recovery_bumps)
        self._spin = 0  # turns left of the recovery spin
        self._unsure = 0  # turns at the path's end, too unsure of the pose to stop
        self.recoveries = 0
        self._cost: NDArray[np.float64] | None = None
        self._visited: deque[NDArray[np.float64]] = deque(maxlen=self.contact_memory)
        self.replans = 0
        self._plan_key: tuple | None = None
        self._plan_map: NDArray[np.bool_] | None = None
        self._last_action: Action | None = None
        self._last_pose: NDArray[np.float64] | None = None
        self._last_turn: Action | None = None
        self._since_plan = 0

    # -- planning --------------------------------------------------------------------------

    @property
    def blocked_points(self) -> list[NDArray[np.float64]]:
        """The contact points (world x, y in m) the plan treats as obstacles."""
        return [c[0] for c in self._contacts]

    def traversable(
        self,
        obstacles: NDArray[np.bool_],
        spec: GridSpec,
        pose: ArrayLike,
        inflation: float | None = None,
        contacts: list[NDArray[np.float64]] | None = None,
    ) -> NDArray[np.bool_]:
        """Cells the robot centre may visit: not within ``inflation`` (default: robot radius +
        margin) of an obstacle or a contact point (default: all of ``blocked_points``), and
        ``navigable`` if the agent was given that (known contact-free cells, e.g. the ground
        truth's). The robot's own footprint is always traversable (mapped obstacles under the robot
        are errors), so a plan can start; contact points are not cleared from under it (a contact
        lies a robot radius ahead, and its cell's centre can fall within the radius)."""
        return self._layers(obstacles, spec, pose, inflation, contacts)[0]

    def _layers(
        self,
        obstacles: NDArray[np.bool_],
        spec: GridSpec,
        pose: ArrayLike,
        inflation: float | None = None,
        contacts: list[NDArray[np.float64]] | None = None,
    ) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
        """:meth:`traversable` and the costmap over it (>= 1 on traversable cells, module docstring)."""
        occ = obstacles.copy()
        near = np.linalg.norm(spec.centres() - np.asarray(pose, float)[:2], axis=-1) <= self.robot_radius
        occ[near] = False
        contacts = self.blocked_points if contacts is None else contacts
        if contacts:  # felt, not mapped: kept even where its cell's centre lies under the footprint
            cells = spec.world_to_cell(np.asarray(contacts))
            cells = cells[spec.contains(cells)]
            occ[cells[:, 0], cells[:, 1]] = True
        inflation = self.inflation if inflation is None else inflation
        clearance = np.full(occ.shape, np.inf)
        if occ.any():
            clearance = distance_transform_edt(~occ) * spec.resolution
        free = clearance > inflation
        if self.navigable is not None:
            free &= self.navigable
        free[near] = True
        cost = 1.0 + self.cost_weight * np.exp(-np.maximum(clearance - inflation, 0.0) / self.cost_decay)
        return free, cost

    @staticmethod
    def _reachable_target(
        free: NDArray[np.bool_], spec: GridSpec, goal: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """The goal, or the centre of the nearest traversable cell when the goal cell is not."""
        cell = spec.world_to_cell(goal)
        if spec.contains(cell) and free[cell[0], cell[1]]:
            return goal
        idx = np.argwhere(free)
        if len(idx) == 0:
            return goal
        centres = spec.cell_to_world(idx)
        return centres[np.argmin(np.linalg.norm(centres - goal, axis=1))]

    def plan(self, pose: ArrayLike, obstacles: NDArray[np.bool_], spec: GridSpec, goal: ArrayLike) -> None:
        """Recompute ``self.path`` (world (N, 2) waypoints, None if no path exists).

        Falls back to a tighter inflation (half the robot radius), to the contact points straight
        ahead of the bumps alone (the side ones are guesses), then to the blocked cells alone
        (fully optimistic) when the map leaves no path, e.g. after mapping errors; when the contacts
        close every way (wedged between hulls), to those straight ahead, to the last bump's alone,
        then to none.
        """
        pose = np.asarray(pose, float)
        goal = np.asarray(goal, float)[:2]
        self.replans += 1
        tight = 0.5 * self.robot_radius
        # The task puts goals where the robot fits: mapped cells within its radius of the goal are
        # errors (e.g. phantoms that made it stop short of an unreachable goal).
        obstacles = obstacles & (np.linalg.norm(spec.centres() - goal, axis=-1) > self.robot_radius)
        empty = np.zeros_like(obstacles)
        ahead = [c[0] for c in self._contacts if c[2]]
        last = [c[0] for c in self._contacts if c[1] == self._bumps]
        # Straight-ahead marks before the last bump's alone: each bump's marks alone leave open the
        # heading of the other, and the robot alternated between two bumped headings.
        attempts = (
            (obstacles, self.inflation, None),
            (obstacles, tight, None),
            (obstacles, tight, ahead),
            (empty, self.inflation, None),
            (empty, tight, ahead),
            (empty, tight, last),
            (empty, tight, []),
        )
        for grid, inflation, contacts in attempts:
            free, cost = self._layers(grid, spec, pose, inflation, contacts)
            target = self._reachable_target(free, spec, goal)
            try:
                path = shortest_path(free, spec, pose[:2], target, cost=cost)
            except ValueError:  # the pose estimate lies off the map
                path = None
            if path is not None and len(path) > 0:
                break
        self._free, self._spec = free, spec
        if path is None or len(path) == 0:
            self.path = self._dense = self._along = None
            logger.debug("no path from %s to %s", pose[:2], goal)
            return
        self.path = np.asarray(path, float)[:, :2]
        self._dense = _densify(self.path, 0.5 * spec.resolution)
        self._along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(self._dense, axis=0), axis=1))])

    # -- acting ----------------------------------------------------------------------------
    def _waypoint(self, xy: NDArray[np.float64]) -> NDArray[np.float64]:
        """The farthest path point at most ``lookahead`` metres (along the path) past the point
        closest to the robot that the robot sees in a straight traversable line."""
        dense, along = self._dense, self._along
        i = int(np.argmin(np.linalg.norm(dense - xy, axis=1)))
        j = int(np.searchsorted(along, along[i] + self.lookahead, side="right")) - 1
        for k in range(j, i, -1):
            if line_of_sight(self._free, self._spec, xy, dense[k]):
                return dense[k]
        # Nothing ahead in a straight line (e.g. just beside the path in a narrow passage): a point
        # some way ahead along the path, not the next one, which may lie beside the robot.
        k = int(np.searchsorted(along, along[i] + min(self.min_waypoint, self.lookahead), side="right")) - 1
        return dense[min(max(k, i + 1), len(dense) - 1)]

    def _turn_or_forward(self, pose: NDArray[np.float64], target: NDArray[np.float64]) -> Action:
        dx, dy = target - pose[:2]
        error = float(wrap_angle(np.arctan2(dy, dx) - pose[2]))
        turn = Action.TURN_LEFT if error > 0 else Action.TURN_RIGHT
        reverse = self._last_turn is not None and turn != self._last_turn
        threshold = self.reverse_turn if reverse and self._clear_ahead(pose) else 0.5
        if abs(error) > threshold * self.turn_step:
            self._last_turn = turn
            return turn
        return Action.FORWARD

    def _clear_ahead(self, pose: NDArray[np.float64]) -> bool:
        """Whether two forward steps along the current heading stay on traversable cells (the
        hysteresis only keeps a heading that does not lead toward an obstacle)."""
        if self._free is None:
            return True
        ahead = pose[:2] + 2.0 * self.forward_step * np.array([np.cos(pose[2]), np.sin(pose[2])])
        return self._spec.contains(self._spec.world_to_cell(ahead)) and line_of_sight(
            self._free, self._spec, pose[:2], ahead
        )

    def act(
        self,
        pose: ArrayLike,
        obstacles: ArrayLike,
        spec: GridSpec,
        goal: ArrayLike,
        bumped: bool | None = None,
        free: ArrayLike | None = None,
        position_sigma: float = 0.0,
    ) -> Action:
        """Next discrete :class:`~vgpnav_env.robot.Action` from the estimated ``pose``,
        the obstacle grid (bool, ``spec.shape``) and the goal (x, y). ``bumped``: whether the last
        action was blocked (a bump sensor); None: a forward step that moved the pose less than
        ``min_progress`` steps was. ``free``: the cells the map has seen free (bool, optional): a
        contact point whose cell it shows free on ``contact_free_frames`` consecutive decisions is
        forgotten. ``position_sigma``: the position standard deviation of the estimate (m; the
        stop rule, module docstring)."""
        pose = np.asarray(pose, float)
        goal = np.asarray(goal, float)[:2]
        obstacles = np.asarray(obstacles, bool)
        if pose.shape != (3,) or not np.all(np.isfinite(pose)):
            raise ValueError(f"pose must be a finite (x, y, yaw), got {pose}")
        if obstacles.shape != spec.shape:
            raise ValueError(
                f"obstacle grid shape {obstacles.shape} does not match the grid spec {spec.shape}"
            )
        blocked = False
        if self._last_action == Action.FORWARD and self._last_pose is not None:
            moved = float(np.linalg.norm(pose[:2] - self._last_pose[:2]))
            blocked = (moved < self.min_progress * self.forward_step) if bumped is None else bool(bumped)
        self.update_contacts(pose[:2], self._last_pose[2] if blocked else None, spec.resolution)
        if free is not None:
            self.reopen_contacts(np.asarray(free, bool), spec)
        self._steps += 1
        if blocked:
            self._bump_steps.append(self._steps)
        action = self._recover(blocked)
        if action is None:
            action = self._decide(pose, obstacles, spec, goal, blocked, float(position_sigma))
        self._last_action, self._last_pose = action, pose
        return action

    def _recover(self, blocked: bool) -> Action | None:
        """The recovery spin (ROS nav2's spin recovery): after ``recovery_bumps`` bumps within
        ``recovery_window`` decisions, one full turn in place (at most ``max_recoveries`` per
        episode) so that the camera maps what the robot keeps bumping into; then a new plan."""
        burst = (
            blocked
            and len(self._bump_steps) == self.recovery_bumps
            and self._bump_steps[-1] - self._bump_steps[0] < self.recovery_window
        )
        if burst and self._spin == 0 and self.recoveries < self.max_recoveries:
            self.recoveries += 1
            self._spin = self.turns_per_circle
            self._bump_steps.clear()
        if self._spin == 0:
            return None
        self._spin -= 1
        if self._spin == 0:
            self.path = None  # plan afresh on what the spin saw
        return Action.TURN_LEFT

    def reopen_contacts(self, free: NDArray[np.bool_], spec: GridSpec) -> None:
        """Count, per contact point at least ``reopen_after`` decisions old, the consecutive calls
        whose ``free`` grid shows its cell free, and forget those seen free ``contact_free_frames``
        times (a phantom contact: what the robot bumped into lies elsewhere, or moved)."""
        kept = []
        for p, bump, straight, seen in self._contacts:
            cell = spec.world_to_cell(p)
            old = self._steps - self._bump_decision.get(bump, self._steps) >= self.reopen_after
            is_free = bool(old and spec.contains(cell) and free[cell[0], cell[1]])
            seen = seen + 1 if is_free else 0
            if seen < self.contact_free_frames:
                kept.append((p, bump, straight, seen))
        if len(kept) < len(self._contacts):
            self.path = None  # a reopened cell may open a shorter way
        self._contacts = kept

    def update_contacts(self, xy: NDArray[np.float64], blocked_yaw: float | None, resolution: float) -> None:
        """Forget the contact points the robot's body now covers (its centre ``xy``, m) and, after a
        blocked forward step heading ``blocked_yaw`` (rad; None: not blocked), mark new ones on the
        robot's front arc (``contact_arc``), half a ``resolution`` cell beyond its radius, except
        where its body stood during the last ``contact_memory`` steps."""
        # A true contact stays a robot radius away; ``contact_clearance`` leaves room for pose noise
        # (hugging a wall must not drop the contacts along it). The side marks of the arc land
        # where the robot came from when it bumped sideways: marks kept there closed a ring around
        # the robot, which then alternated between the two headings the last bump's marks left open.
        xy = np.asarray(xy, float)
        self._visited.append(xy)
        clear = self.contact_clearance
        self._contacts = [c for c in self._contacts if np.linalg.norm(c[0] - xy) > clear]
        if blocked_yaw is not None:
            self._bumps += 1
            self._bump_decision[self._bumps] = self._steps
            ahead = self.robot_radius + 0.5 * resolution
            yaw = blocked_yaw + self.contact_arc
            marks = xy + ahead * np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
            visited = np.asarray(self._visited)
            covered = np.linalg.norm(marks[:, None] - visited[None], axis=-1).min(axis=1) <= clear
            covered &= self.contact_arc != 0.0  # the heading that bumped stays closed from here
            arc = self.contact_arc[~covered]
            self._contacts.extend(
                (p, self._bumps, bool(a == 0.0), 0) for p, a in zip(marks[~covered], arc, strict=True)
            )

    def _path_clear(self, free: NDArray[np.bool_], xy: NDArray[np.float64]) -> bool:
        """Whether the rest of the current path (from the point closest to ``xy``) stays on ``free``."""
        rest = self._dense[int(np.argmin(np.linalg.norm(self._dense - xy, axis=1))) :]
        cells = self._spec.world_to_cell(rest)
        return bool(np.all(self._spec.contains(cells)) and np.all(free[cells[:, 0], cells[:, 1]]))

    def _sure_within(self, distance: float, sigma: float) -> bool:
        """Whether the goal lies within the success radius given the estimate's uncertainty."""
        return distance + self.stop_z * sigma <= self.success_radius

    def _decide(
        self,
        pose: NDArray,
        obstacles: NDArray[np.bool_],
        spec: GridSpec,
        goal: NDArray,
        blocked: bool,
        sigma: float = 0.0,
    ) -> Action:
        distance = float(np.linalg.norm(goal - pose[:2]))
        near = distance <= self.goal_radius or (blocked and distance <= self.blocked_goal_radius)
        if near and self._sure_within(distance, sigma):
            return Action.STOP  # at the goal, or bumped into something just short of it
        if self._plan_key is not None and spec == self._plan_key[0]:
            planned = np.asarray(self._plan_key[1])
            if np.linalg.norm(goal - planned) <= 0.5 * spec.resolution:
                goal = planned  # the same goal, up to the float32 of an observation's goal_rel
        key = (spec, tuple(goal))
        changed = (
            self._plan_map is None or key != self._plan_key or not np.array_equal(obstacles, self._plan_map)
        )
        strayed = (
            self._dense is not None
            and np.min(np.linalg.norm(self._dense - pose[:2], axis=1)) > self.off_path_distance
        )
        self._since_plan += 1
        if changed and not (blocked or strayed or self.path is None or key != self._plan_key):
            # A fused map changes on every frame: keep the path while it stays clear (replanning
            # each step let the plan, hence the heading, flip between near-equal routes).
            free = self.traversable(obstacles, spec, pose)
            if self._since_plan < self.replan_every and self._path_clear(free, pose[:2]):
                self._free, self._plan_map, changed = free, obstacles.copy(), False
        if changed or blocked or strayed or self.path is None:
            self.plan(pose, obstacles, spec, goal)
            self._plan_key, self._plan_map, self._since_plan = key, obstacles.copy(), 0
        if self.path is None:  # off the map: head for the goal, turning away after a bump
            return Action.TURN_LEFT if blocked else self._turn_or_forward(pose, goal)
        if np.linalg.norm(self.path[-1] - pose[:2]) < 0.5 * self.forward_step:
            if self._sure_within(distance, sigma) or self._unsure >= self.turns_per_circle:
                return Action.STOP  # at the reachable point closest to an unreachable goal
            self._unsure += 1  # too unsure to stop here: one turn in place for a better fix
            return Action.TURN_LEFT
        self._unsure = 0
        return self._turn_or_forward(pose, self._waypoint(pose[:2]))
