"""The robot's MuJoCo body (slide x, slide y, hinge yaw) with a hidden cylinder, and
collision-checked motion through MuJoCo contacts.

The robot cylinder spans heights [``clearance``, ``height``] above the floor (the same band the
ground-truth occupancy calls obstacles; defaults from :mod:`vgpnav_env.robot`), lives in geom
group 3 (hidden from the robot's camera) and collides with every geom whose
``contype``/``conaffinity`` is 1. Poses are (x, y, yaw) in W, metres and radians, yaw
counter-clockwise from +x; motions are paths of :mod:`vgpnav_env.robot`.
"""

from __future__ import annotations

import mujoco
import numpy as np
from numpy.typing import ArrayLike, NDArray

from vgpnav_env.geometry import wrap_angle
from vgpnav_env.robot import OBSTACLE_MIN, ROBOT_HEIGHT, ROBOT_RADIUS, Path

ROBOT_BODY = "vgpnav_robot"
ROBOT_GEOM = "vgpnav_robot_hull"
_JOINTS = ("vgpnav_robot_x", "vgpnav_robot_y", "vgpnav_robot_yaw")

#: Distance between collision samples along a motion before bisection (metres).
SAMPLE_SPACING = 0.05
#: Bisection iterations between the last free and the first colliding sample (~1 mm at 0.05 m).
BISECTION_STEPS = 6


def add_robot(
    spec: mujoco.MjSpec,
    radius: float = ROBOT_RADIUS,
    height: float = ROBOT_HEIGHT,
    clearance: float = OBSTACLE_MIN,
) -> None:
    """Add the robot body (planar joints + hidden collision cylinder) to a scene's ``MjSpec``."""
    if not 0.0 < radius < 2.0:
        raise ValueError(f"robot radius must be in (0, 2) metres, got {radius}")
    if not 0.0 <= clearance < height:
        raise ValueError(f"need 0 <= clearance < height, got clearance={clearance}, height={height}")
    body = spec.worldbody.add_body(name=ROBOT_BODY, pos=[0.0, 0.0, 0.0])
    for name, axis in zip(_JOINTS[:2], ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0]), strict=True):
        body.add_joint(name=name, type=mujoco.mjtJoint.mjJNT_SLIDE, axis=axis)
    body.add_joint(name=_JOINTS[2], type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0.0, 0.0, 1.0])
    half = 0.5 * (height - clearance)
    body.add_geom(
        name=ROBOT_GEOM,
        type=mujoco.mjtGeom.mjGEOM_CYLINDER,
        size=[radius, half, 0.0],
        pos=[0.0, 0.0, clearance + half],
        group=3,
        contype=1,
        conaffinity=1,
        mass=10.0,
    )


class PlanarRobot:
    """State and collision-checked motion of the robot body in one ``MjData``."""

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData | None = None) -> None:
        self.model = model
        self.data = data if data is not None else mujoco.MjData(model)
        try:
            self._qpos = np.array([model.jnt_qposadr[model.joint(n).id] for n in _JOINTS])
            self._geom = model.geom(ROBOT_GEOM).id
        except KeyError as e:
            raise ValueError("model has no robot body; build it with envs.body.add_robot") from e

    @property
    def pose(self) -> NDArray[np.float64]:
        """Current (x, y, yaw) with yaw wrapped into [-pi, pi)."""
        x, y, yaw = self.data.qpos[self._qpos]
        return np.array([x, y, float(wrap_angle(yaw))])

    def set_pose(self, pose: ArrayLike) -> None:
        """Place the robot at (x, y, yaw) without any collision check."""
        x, y, yaw = np.asarray(pose, float)
        self.data.qpos[self._qpos] = (x, y, float(wrap_angle(yaw)))
        mujoco.mj_kinematics(self.model, self.data)

    def in_collision(self, pose: ArrayLike | None = None) -> bool:
        """Whether the robot hull penetrates any scene geom at ``pose`` (default: current pose).

        The robot is left at ``pose``.
        """
        if pose is not None:
            self.set_pose(pose)
        mujoco.mj_collision(self.model, self.data)
        n = self.data.ncon
        if n == 0:
            return False
        c = self.data.contact
        g1, g2, dist = c.geom1[:n], c.geom2[:n], c.dist[:n]
        return bool(np.any(((g1 == self._geom) | (g2 == self._geom)) & (dist < 0.0)))

    def move_along(self, path: Path, length: float) -> tuple[float, bool]:
        """Follow ``path(s)`` (pose at s in [0, 1], ``path(0)`` = current pose) as far as it is free.

        Samples every ``SAMPLE_SPACING`` metres of ``length`` (path length, metres; rotations count
        with the hull radius), bisects the first blocked interval and leaves the robot at the last
        collision-free pose. Returns (fraction travelled in [0, 1], blocked).
        """
        start = self.pose
        n = max(1, int(np.ceil(length / SAMPLE_SPACING)))
        free = 0.0
        for i in range(1, n + 1):
            s = i / n
            if self.in_collision(path(s)):
                lo, hi = free, s
                for _ in range(BISECTION_STEPS):
                    mid = 0.5 * (lo + hi)
                    if self.in_collision(path(mid)):
                        hi = mid
                    else:
                        lo = mid
                self.set_pose(path(lo) if lo > 0.0 else start)
                return lo, True
            free = s
        return 1.0, False
