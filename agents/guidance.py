"""Planner guidance for learned policies (a hierarchical recipe option, ``--guidance path``).

The agent's own A* path on its *estimated* map -- :class:`~vgpnav_env.agents.astar.AStarAgent`
planning on the perception wrapper's ``fused_map`` from the estimated pose to the goal the
observation gives (pose + ``goal_rel``) -- drawn into a channel aligned with the observation's
egocentric map crop, as Active Neural SLAM's global planner hands its local policy a short-term
goal. Beside the channel, the ``waypoint`` on that path :data:`LOOKAHEAD` m ahead (distance m,
bearing rad from the estimated heading; the goal itself when there is no path), the short-term goal
of Active Neural SLAM. When the observation carries the bump sensor (``agents.proprioception``), a
blocked forward step marks contact points on the robot's front, as ``AStarAgent`` does, and the path
goes around them (an obstacle the map does not hold no longer pins the path, and the policy following
it, to a wall) until the map sees their cells free. Nothing privileged: the same inputs as
``PerceptionAStar``. The policy then
learns the local part (following the path, stopping at the goal); the plain recipe has to learn
the planning too.

:class:`PathChannel` computes the channel; :class:`PathGuidance` adds it to the observations of a
perception-wrapped env (training); a policy evaluated in an env without the wrapper computes it
with its own :class:`PathChannel` from the same env (``SB3Policy``).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

from vgpnav_env.agents.astar import REOPEN_FREE, AStarAgent, _densify
from vgpnav_env.agents.proprioception import BUMPED_KEY, LAST_ACTION_KEY
from vgpnav_env.geometry import wrap_angle
from vgpnav_env.robot import Action

#: Observation keys of the path channel and of the waypoint, and the guidance kinds (None: plain).
PATH_KEY, WAYPOINT_KEY = "path", "waypoint"
GUIDANCE = ("path",)
#: Pixel values of the channel: the path, and the goal (3x3 pixels, when inside the crop).
PATH_VALUE, GOAL_VALUE = 128, 255
#: Distance (m, along the path) of the waypoint ahead of the path point closest to the robot.
LOOKAHEAD = 0.5


class PathChannel:
    """The A* path from the estimated pose to the goal in the egocentric crop frame of
    :meth:`~vgpnav_env.perception.occupancy.LogOddsMap.egocentric_crop` (row 0 ahead, columns to
    the right, ``resolution`` metres per pixel): ``(1, size, size)`` uint8, :data:`PATH_VALUE` on
    the path, :data:`GOAL_VALUE` at the goal, 0 elsewhere. Replans (:meth:`_replan`) when newly
    occupied cells block the path, the robot strays ``replan_distance`` m from it, a blocked forward
    step adds contact points (module docstring), and every ``replan_every`` steps (cells that became
    free may open a shorter way)."""

    def __init__(
        self,
        size: int,
        resolution: float,
        robot_radius: float,
        replan_distance: float = 0.3,
        replan_every: int = 10,
    ) -> None:
        self.size, self.resolution = int(size), float(resolution)
        self.planner = AStarAgent(robot_radius=robot_radius)
        self.replan_distance, self.replan_every = float(replan_distance), int(replan_every)
        self.reset()

    def reset(self) -> None:
        self.planner.reset()
        self._key: tuple | None = None
        self._occupied: NDArray[np.bool_] | None = None
        self._dense: NDArray[np.float64] | None = None
        self._along = np.zeros(0)
        self._since = 0

    def _replan(self, occupied: NDArray[np.bool_], spec: Any, goal: NDArray, xy: NDArray) -> bool:
        """Whether to plan again: a new goal or grid, no path, strayed from it, every
        ``replan_every`` steps, or a newly occupied cell within the robot's inflation of the path."""
        if (
            self._dense is None
            or self._key != (spec, tuple(goal.round(3)))
            or self._since >= self.replan_every
        ):
            return True
        if np.min(np.linalg.norm(self._dense - xy, axis=1)) > self.replan_distance:
            return True
        new = np.argwhere(occupied & ~self._occupied)
        if len(new) == 0:
            return False
        points = spec.cell_to_world(new)
        near = self.planner.inflation + spec.resolution
        return bool((np.linalg.norm(points[:, None] - self._dense[None], axis=-1) < near).any())

    def __call__(self, obs: dict[str, Any], fused_map: Any) -> dict[str, NDArray]:
        """``{PATH_KEY: (1, size, size) uint8 channel, WAYPOINT_KEY: (distance m, bearing rad)}``."""
        x, y, yaw = np.asarray(obs["pose"], float)
        dist, bearing = np.asarray(obs["goal_rel"], float)
        goal = np.array([x + dist * np.cos(yaw + bearing), y + dist * np.sin(yaw + bearing)])
        occupied = fused_map.occupied()
        bumped = bool(obs.get(BUMPED_KEY)) and obs.get(LAST_ACTION_KEY) == Action.FORWARD
        self.planner.update_contacts(np.array([x, y]), yaw if bumped else None, fused_map.spec.resolution)
        self.planner.reopen_contacts(fused_map.floor_seen(REOPEN_FREE), fused_map.spec)
        if bumped or self._replan(occupied, fused_map.spec, goal, np.array([x, y])):
            self.planner.plan((x, y, yaw), occupied, fused_map.spec, goal)
            path = self.planner.path
            self._dense = None if path is None else _densify(path, 0.5 * self.resolution)
            if self._dense is not None:
                steps = np.linalg.norm(np.diff(self._dense, axis=0), axis=1)
                self._along = np.concatenate([[0.0], np.cumsum(steps)])
            self._key, self._since = (fused_map.spec, tuple(goal.round(3))), 0
        self._occupied = occupied
        self._since += 1
        out = np.zeros((1, self.size, self.size), np.uint8)
        waypoint = goal
        if self._dense is not None:
            self._draw(out[0], self._dense, (x, y, yaw), PATH_VALUE, 0)
            i = int(np.argmin(np.linalg.norm(self._dense - (x, y), axis=1)))
            j = int(np.searchsorted(self._along, self._along[i] + LOOKAHEAD))
            waypoint = self._dense[min(j, len(self._dense) - 1)]
        self._draw(out[0], goal[None], (x, y, yaw), GOAL_VALUE, 1)
        d = waypoint - (x, y)
        polar = np.array([np.hypot(*d), wrap_angle(np.arctan2(d[1], d[0]) - yaw)], np.float32)
        return {PATH_KEY: out, WAYPOINT_KEY: polar}

    def _draw(
        self, img: NDArray[np.uint8], xy: NDArray[np.float64], pose: tuple, value: int, grow: int
    ) -> None:
        x, y, yaw = pose
        d = xy - (x, y)
        ahead = d[:, 0] * np.cos(yaw) + d[:, 1] * np.sin(yaw)
        right = d[:, 0] * np.sin(yaw) - d[:, 1] * np.cos(yaw)
        centre = (self.size - 1) / 2.0
        rows = np.rint(centre - ahead / self.resolution).astype(int)
        cols = np.rint(centre + right / self.resolution).astype(int)
        for dr in range(-grow, grow + 1):
            for dc in range(-grow, grow + 1):
                r, c = rows + dr, cols + dc
                inside = (r >= 0) & (r < self.size) & (c >= 0) & (c < self.size)
                img[r[inside], c[inside]] = value


def path_channel_for(env: gym.Env, space: spaces.Dict) -> PathChannel:
    """A :class:`PathChannel` matching the map crop of ``space`` in the perception-wrapped ``env``."""
    resolution = float(env.get_wrapper_attr("map_resolution"))
    return PathChannel(space["map"].shape[-1], resolution, env.unwrapped.robot_radius)


class PathGuidance(gym.Wrapper):
    """Adds the :class:`PathChannel`'s channel (:data:`PATH_KEY`) and waypoint
    (:data:`WAYPOINT_KEY`) to a perception wrapper's observations."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        space = env.observation_space
        self.observation_space = spaces.Dict(
            {**space.spaces, PATH_KEY: space["map"], WAYPOINT_KEY: space["goal_rel"]}
        )
        self.channel = path_channel_for(env, env.observation_space)

    def _add(self, obs: dict[str, Any]) -> dict[str, Any]:
        return {**obs, **self.channel(obs, self.env.get_wrapper_attr("fused_map"))}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        self.channel.reset()
        return self._add(obs), info

    def step(self, action: Any):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return self._add(obs), reward, terminated, truncated, info
