"""Frames, rigid transforms and the pinhole camera: the one place for geometry.

Conventions (see DESIGN.md):

- World frame W: metric, right-handed, z up, floor at z = 0.
- Camera frame C: OpenCV (x right, y down, z forward).
- Poses are ``T_wc`` (4x4, maps camera coordinates into the world) unless a name
  says otherwise; ``T_ij`` maps frame j into frame i.
- MuJoCo cameras look along their own -z with +y up; ``R_cv = R_mj @ diag(1, -1, -1)``.
- Depth is metric z-depth along the optical axis. Angles are radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

#: Rotation between a MuJoCo camera frame and an OpenCV camera frame (its own inverse).
MUJOCO_TO_OPENCV = np.diag([1.0, -1.0, -1.0])


def make_pose(rotation: ArrayLike | Rotation, translation: ArrayLike) -> NDArray[np.float64]:
    """4x4 homogeneous transform from a 3x3 rotation (or scipy Rotation) and a translation."""
    R = rotation.as_matrix() if isinstance(rotation, Rotation) else np.asarray(rotation, float)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(translation, float)
    return T


def invert_pose(T: ArrayLike) -> NDArray[np.float64]:
    """Inverse of a rigid 4x4 transform (or a stack (..., 4, 4))."""
    T = np.asarray(T, float)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def transform_points(T: ArrayLike, points: ArrayLike) -> NDArray[np.float64]:
    """Apply a 4x4 transform to points of shape (..., 3)."""
    T = np.asarray(T, float)
    P = np.asarray(points, float)
    return P @ T[:3, :3].T + T[:3, 3]


def yaw_pitch_rotation(yaw: float, pitch: float, roll: float = 0.0) -> NDArray[np.float64]:
    """Rotation ``R_wc`` of an OpenCV camera in W.

    ``yaw`` is the heading of the optical axis in the xy-plane, counter-clockwise from +x;
    ``pitch`` > 0 tilts the optical axis down; ``roll`` turns about the optical axis.
    At yaw = pitch = roll = 0 the camera looks along +x with image-down along -z.
    """
    # Level camera looking along +x: columns are the camera axes expressed in W.
    level = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    R_yaw = Rotation.from_euler("z", yaw).as_matrix()
    # Pitch down = rotation about the camera's +x axis (right) by -pitch in OpenCV axes.
    R_tilt = Rotation.from_euler("xz", [-pitch, roll]).as_matrix()
    return R_yaw @ level @ R_tilt


def camera_pose(position: ArrayLike, yaw: float, pitch: float, roll: float = 0.0) -> NDArray[np.float64]:
    """``T_wc`` of an OpenCV camera at ``position`` (W, metres) with the given yaw/pitch/roll."""
    return make_pose(yaw_pitch_rotation(yaw, pitch, roll), position)


def camera_yaw_pitch(T_wc: ArrayLike) -> tuple[float, float]:
    """Heading (counter-clockwise from +x) and downward pitch of a camera's optical axis."""
    z = np.asarray(T_wc, float)[:3, 2]
    yaw = float(np.arctan2(z[1], z[0]))
    pitch = float(-np.arcsin(np.clip(z[2], -1.0, 1.0)))
    return yaw, pitch


def opencv_from_mujoco(R_mj: ArrayLike) -> NDArray[np.float64]:
    """World rotation of the OpenCV camera frame from a MuJoCo camera's ``cam_xmat``."""
    return np.asarray(R_mj, float).reshape(3, 3) @ MUJOCO_TO_OPENCV


def mujoco_from_opencv(R_cv: ArrayLike) -> NDArray[np.float64]:
    """MuJoCo camera world rotation (looks along -z, +y up) from an OpenCV ``R_wc``."""
    return np.asarray(R_cv, float).reshape(3, 3) @ MUJOCO_TO_OPENCV


def rotation_angle(R_a: ArrayLike, R_b: ArrayLike) -> float:
    """Geodesic angle (radians) between two rotation matrices."""
    R = np.asarray(R_a, float).T @ np.asarray(R_b, float)
    return float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


def wrap_angle(angle: ArrayLike) -> NDArray[np.float64] | float:
    """Wrap angles (radians) into [-pi, pi)."""
    return (np.asarray(angle, float) + np.pi) % (2.0 * np.pi) - np.pi


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole camera from MuJoCo's vertical field of view and an image size.

    ``fovy`` is in radians. Square pixels; principal point ((W-1)/2, (H-1)/2), as MuJoCo
    renders. Pixel (u, v) has u along the image width (x) and v along the height (y).
    """

    width: int
    height: int
    fovy: float

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if not 0.0 < self.fovy < np.pi:
            raise ValueError(f"fovy must be in (0, pi) radians, got {self.fovy}")

    @property
    def focal(self) -> float:
        return 0.5 * self.height / np.tan(0.5 * self.fovy)

    @property
    def K(self) -> NDArray[np.float64]:
        f = self.focal
        return np.array(
            [[f, 0.0, (self.width - 1) / 2.0], [0.0, f, (self.height - 1) / 2.0], [0.0, 0.0, 1.0]]
        )

    @property
    def fovx(self) -> float:
        return 2.0 * float(np.arctan(0.5 * self.width / self.focal))

    def resized(self, width: int, height: int) -> PinholeCamera:
        """Same vertical field of view at another image size."""
        return PinholeCamera(width, height, self.fovy)

    def project(self, points_c: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Pixels (..., 2) and z-depths (...) of camera-frame points (..., 3)."""
        P = np.asarray(points_c, float)
        z = P[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = P[..., :2] / z[..., None]
        K = self.K
        uv = uv * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]
        return uv, z

    def project_world(
        self, T_wc: ArrayLike, points_w: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Pixels and z-depths of world points seen from a camera at ``T_wc``."""
        return self.project(transform_points(invert_pose(T_wc), points_w))

    def rays(self) -> NDArray[np.float64]:
        """Camera-frame directions (H, W, 3) with z = 1 through every pixel centre."""
        K = self.K
        u, v = np.meshgrid(np.arange(self.width, dtype=float), np.arange(self.height, dtype=float))
        return np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)

    def backproject(self, depth: ArrayLike) -> NDArray[np.float64]:
        """Camera-frame points (H, W, 3) from a z-depth map (H, W)."""
        depth = np.asarray(depth, float)
        if depth.shape != (self.height, self.width):
            raise ValueError(f"depth shape {depth.shape} does not match camera {(self.height, self.width)}")
        return self.rays() * depth[..., None]

    def backproject_world(
        self, depth: ArrayLike, T_wc: ArrayLike, mask: ArrayLike | None = None
    ) -> NDArray[np.float64]:
        """World points (N, 3) of the pixels with finite positive depth (and ``mask``)."""
        depth = np.asarray(depth, float)
        valid = np.isfinite(depth) & (depth > 0)
        if mask is not None:
            valid &= np.asarray(mask, bool)
        return transform_points(T_wc, self.backproject(depth)[valid])
