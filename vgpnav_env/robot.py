"""The robot's description: body, camera, obstacle height band, discrete actions and motion model.

The one home of what the robot is. The env, the VGP-Nav wrapper, the agents, the ground-truth maps,
the database/query builds and the perception defaults read these values from here.

- Body: a disc of radius :data:`ROBOT_RADIUS` m up to :data:`ROBOT_HEIGHT` m above the floor.
- Camera: OpenCV camera at :data:`CAMERA_HEIGHT` m above the floor on the robot's centre, looking
  along the robot's heading, pitched :data:`CAMERA_PITCH_DEG` degrees down, vertical field of view
  :data:`FOVY_DEG` degrees.
- Obstacle height band: anything between :data:`OBSTACLE_MIN` m and the robot height (ground
  truth) or the camera height (perception) above the floor is an obstacle; points within
  :data:`FLOOR_TOLERANCE` m of the floor are free ground.
- Actions: :class:`Action` = {stop, forward :data:`FORWARD_STEP` m, turn left / right
  :data:`TURN_STEP_DEG` degrees}; :func:`predict_pose` is their nominal motion (no collisions).

Planar poses are (x, y, yaw) in W: metres, radians, yaw counter-clockwise from +x.
"""

from __future__ import annotations

from collections.abc import Callable
from enum import IntEnum
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vgpnav_env.geometry import camera_pose, camera_yaw_pitch, wrap_angle

ROBOT_RADIUS = 0.2
ROBOT_HEIGHT = 1.3
CAMERA_HEIGHT = 1.2
CAMERA_PITCH_DEG = 20.0
FOVY_DEG = 60.0
OBSTACLE_MIN = 0.15
FLOOR_TOLERANCE = 0.05
FORWARD_STEP = 0.25
TURN_STEP_DEG = 15.0

#: A pose along a motion at s in [0, 1] (s = 0: the start pose).
Path = Callable[[float], NDArray[np.float64]]


class Action(IntEnum):
    """The discrete actions (``Discrete(4)`` of the point-goal env)."""

    STOP = 0
    FORWARD = 1
    TURN_LEFT = 2
    TURN_RIGHT = 3


def felt_contact(env: Any, action: Any) -> bool:
    """Whether ``action`` was a discrete forward step that the bump sensor of ``env`` (a point-goal
    env or a wrapper of one: ``env.unwrapped.bumped``) found blocked: something the robot touched
    lies ahead."""
    base = env.unwrapped
    return base.action_mode == "discrete" and base.bumped and int(action) == Action.FORWARD


def camera_T_wc(
    pose: ArrayLike, height: float = CAMERA_HEIGHT, pitch: float = float(np.radians(CAMERA_PITCH_DEG))
) -> NDArray[np.float64]:
    """OpenCV camera pose ``T_wc`` (4x4) of the robot at ``pose``: camera ``height`` m above the
    floor, ``pitch`` radians down."""
    x, y, yaw = np.asarray(pose, float)
    return camera_pose([x, y, height], float(yaw), pitch)


def base_pose(T_wc: ArrayLike) -> NDArray[np.float64]:
    """The planar pose (x, y, yaw) of the robot carrying the camera ``T_wc`` (its optical axis' heading)."""
    T_wc = np.asarray(T_wc, float)
    return np.array([T_wc[0, 3], T_wc[1, 3], camera_yaw_pitch(T_wc)[0]])


def straight_path(pose: ArrayLike, distance: float) -> Path:
    """Translation by ``distance`` metres along the heading of ``pose``."""
    x, y, yaw = np.asarray(pose, float)
    d = np.array([np.cos(yaw), np.sin(yaw), 0.0]) * distance
    return lambda s: np.array([x, y, yaw]) + s * d


def turn_path(pose: ArrayLike, angle: float) -> Path:
    """Rotation in place by ``angle`` radians (counter-clockwise positive)."""
    x, y, yaw = np.asarray(pose, float)
    return lambda s: np.array([x, y, yaw + s * angle])


def arc_path(pose: ArrayLike, v: float, omega: float, dt: float) -> Path:
    """Unicycle motion at constant linear speed ``v`` (m/s) and turn rate ``omega`` (rad/s) for ``dt`` s."""
    x, y, yaw = np.asarray(pose, float)

    def at(s: float) -> NDArray[np.float64]:
        t = s * dt
        if abs(omega) < 1e-9:
            return np.array([x + v * t * np.cos(yaw), y + v * t * np.sin(yaw), yaw])
        r = v / omega
        yaw_t = yaw + omega * t
        return np.array([x + r * (np.sin(yaw_t) - np.sin(yaw)), y - r * (np.cos(yaw_t) - np.cos(yaw)), yaw_t])

    return at


def action_path(
    pose: ArrayLike,
    action: int,
    forward_step: float = FORWARD_STEP,
    turn_step: float = float(np.radians(TURN_STEP_DEG)),
    radius: float = ROBOT_RADIUS,
) -> tuple[Path, float] | None:
    """The nominal motion of a discrete ``action`` from ``pose``: (path, length for collision
    sampling in metres, turns counted at the hull ``radius``); None for ``STOP``.
    ``turn_step`` is in radians."""
    action = Action(int(action))
    if action == Action.STOP:
        return None
    if action == Action.FORWARD:
        return straight_path(pose, forward_step), forward_step
    angle = turn_step if action == Action.TURN_LEFT else -turn_step
    return turn_path(pose, angle), abs(angle) * radius


def velocity_path(pose: ArrayLike, v: float, omega: float, dt: float, radius: float = ROBOT_RADIUS):
    """The unicycle motion of a continuous command: (path, length in metres with turns counted at
    the hull ``radius``)."""
    return arc_path(pose, v, omega, dt), abs(v) * dt + abs(omega) * dt * radius


def predict_pose(
    pose: ArrayLike,
    action: int,
    forward_step: float = FORWARD_STEP,
    turn_step: float = float(np.radians(TURN_STEP_DEG)),
) -> NDArray[np.float64]:
    """Where ``action`` takes the robot from ``pose`` if nothing blocks it (turns wrap the yaw into
    [-pi, pi)).

    The end of :func:`action_path`: the env's collision-free motion, the wrapper's dead reckoning
    and the agents' expectations all use this model. ``turn_step`` is in radians.
    """
    motion = action_path(pose, action, forward_step, turn_step)
    if motion is None:
        return np.array(pose, float)
    end = motion[0](1.0)
    if Action(int(action)) != Action.FORWARD:  # a turn: keep the yaw in range (forward keeps it)
        end[2] = float(wrap_angle(end[2]))
    return end
