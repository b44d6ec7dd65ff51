"""Resection: the metric pose from points the references' known poses triangulate.

Stage 4 refinement of a metric pose ``T_wq`` (OpenCV camera -> world, metres). A query keypoint
matched in two or more references (:attr:`BackboneOutput.matches`, per reference (m_i, 4) pixels
``(u_q, v_q, u_i, v_i)``; one keypoint has the same query pixel in every pair) is triangulated from
those references alone: their poses ``T_wi`` are known and metric, so the point is metric and does
not depend on the query's pose or on the ground scale. The query pose then follows from the 2D-3D
correspondences (poselib's LO-RANSAC P3P with a non-linear refinement). Only matches the pose to
refine explains (:func:`~vgpnav_env.perception.verify.support.explained_matches`) enter, so the
resection refines that pose and does not jump to another place; it is repeated from the refined
pose ``iterations`` times. A last step refines the resected pose on both kinds of evidence at
once (poselib's hybrid pose, LO-RANSAC started from it): the triangulated points by reprojection
and every explained match, also those seen in one reference only, by its epipolar error to that
reference's known pose. On plain walls few keypoints are matched in two references; their single
matches still constrain the pose.

Motion averaging places the centre from the directions of the pairs' translations, whose errors
grow with the distance along each ray; the triangulated points fix the centre by reprojection
instead.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import poselib
from numpy.typing import NDArray

from vgpnav_env.geometry import PinholeCamera, invert_pose, make_pose
from vgpnav_env.perception.backbones.classical import poselib_camera
from vgpnav_env.perception.verify.support import explained_matches

#: Decimals of the query pixel that identify one keypoint across pairs.
_KEY_DECIMALS = 2


@dataclass(frozen=True)
class ResectionConfig:
    """Resection settings; pixels at the perceived camera's focal length.

    Attributes:
        epipolar_px: a match enters when the pose to refine explains it within this Sampson distance.
        reprojection_px: a triangulated point is kept when it reprojects into each of its
            references within this; the resection's RANSAC inlier threshold as well.
        min_angle_deg: a point's rays from its references must span at least this angle.
        min_inliers: the resected pose stands only with at least this many inlier points.
        iterations: resections in a row, each from the last one's pose (0: off).
        hybrid_epipolar_px: the hybrid step's inlier threshold for single matches (Sampson
            distance; None: no hybrid step).
    """

    epipolar_px: float = 4.5
    reprojection_px: float = 3.0
    min_angle_deg: float = 0.5
    min_inliers: int = 12
    iterations: int = 2
    hybrid_epipolar_px: float | None = 1.0

    def __post_init__(self) -> None:
        if min(self.epipolar_px, self.reprojection_px) <= 0 or self.min_angle_deg < 0:
            raise ValueError("resection needs positive pixel thresholds and a non-negative angle")
        if self.hybrid_epipolar_px is not None and self.hybrid_epipolar_px <= 0:
            raise ValueError(f"hybrid_epipolar_px must be > 0 px or None, got {self.hybrid_epipolar_px}")
        if self.min_inliers < 4 or self.iterations < 0:
            raise ValueError(
                f"resection needs min_inliers >= 4 and iterations >= 0, "
                f"got {self.min_inliers} and {self.iterations}"
            )


@dataclass(frozen=True)
class Resection:
    """A resection's outcome: the pose ``T_wq`` (None when it did not stand) and its inlier
    points ``n_inliers``."""

    T_wq: NDArray[np.float64] | None
    n_inliers: int


def reference_points(
    T_wi: NDArray[np.float64],
    matches: Sequence[NDArray[np.floating]],
    camera: PinholeCamera,
    max_reprojection_px: float,
    min_angle_deg: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Query pixels (n, 2) and their world points (n, 3), metres: each query keypoint matched in
    two or more references, triangulated from those references' poses ``T_wi`` (linear DLT); kept
    when in front of every reference, within ``max_reprojection_px`` of each observation and seen
    from rays at least ``min_angle_deg`` apart."""
    rows = [(np.asarray(m, float).reshape(-1, 4), i) for i, m in enumerate(matches)]
    if not rows:
        return np.zeros((0, 2)), np.zeros((0, 3))
    uv = np.concatenate([m for m, _ in rows])
    ref = np.concatenate([np.full(len(m), i) for m, i in rows]).astype(int)
    keys, track = np.unique(np.round(uv[:, :2], _KEY_DECIMALS), axis=0, return_inverse=True)
    track = track.reshape(-1)
    # One observation per reference and keypoint; tracks of two or more references.
    _, first = np.unique(track * len(T_wi) + ref, return_index=True)
    uv, ref, track = uv[first], ref[first], track[first]
    count = np.bincount(track, minlength=len(keys))
    P = camera.K @ invert_pose(T_wi)[:, :3]  # (k, 3, 4) world -> reference pixels
    centres = T_wi[:, :3, 3]
    pixels, points = [], []
    for c in np.unique(count[count >= 2]):
        tracks = np.flatnonzero(count == c)
        sel = np.isin(track, tracks)
        order = np.argsort(track[sel], kind="stable")
        obs_uv, obs_ref = uv[sel][order, 2:].reshape(-1, c, 2), ref[sel][order].reshape(-1, c)
        Ps = P[obs_ref]  # (n, c, 3, 4)
        rows_u = obs_uv[..., 0:1] * Ps[:, :, 2] - Ps[:, :, 0]
        rows_v = obs_uv[..., 1:2] * Ps[:, :, 2] - Ps[:, :, 1]
        A = np.concatenate([rows_u, rows_v], axis=1)  # (n, 2c, 4)
        X = np.linalg.svd(A)[2][:, -1]
        with np.errstate(divide="ignore", invalid="ignore"):
            X = X[:, :3] / X[:, 3:]
        proj = np.einsum("ncij,nj->nci", Ps, np.c_[X, np.ones(len(X))])
        with np.errstate(divide="ignore", invalid="ignore"):
            err = np.linalg.norm(proj[..., :2] / proj[..., 2:] - obs_uv, axis=2)
        rays = X[:, None] - centres[obs_ref]
        rays /= np.linalg.norm(rays, axis=2, keepdims=True)
        cosines = np.einsum("nai,nbi->nab", rays, rays).min(axis=(1, 2))
        ok = (
            np.isfinite(X).all(axis=1)
            & (proj[..., 2] > 0).all(axis=1)
            & (np.nan_to_num(err, nan=np.inf) <= max_reprojection_px).all(axis=1)
            & (cosines <= np.cos(np.radians(min_angle_deg)))
        )
        pixels.append(keys[tracks[ok]])
        points.append(X[ok])
    if not points:
        return np.zeros((0, 2)), np.zeros((0, 3))
    return np.concatenate(pixels), np.concatenate(points)


def resect(
    T_wq: NDArray[np.float64],
    T_wi: NDArray[np.float64],
    matches: Sequence[NDArray[np.floating]],
    camera: PinholeCamera,
    config: ResectionConfig,
) -> Resection:
    """The pose ``T_wq`` refined by resection on the points the references ``T_wi`` (k, 4, 4)
    triangulate from the matches it explains, then by the hybrid step (see the module docstring).
    ``T_wq`` None in the result when fewer than ``config.min_inliers`` points support a pose; a
    later iteration that fails keeps the earlier one's pose."""
    intrinsics = poselib_camera(camera)
    pose, result = np.asarray(T_wq, float), Resection(None, 0)
    hybrid = config.hybrid_epipolar_px is not None and config.iterations > 0
    for step in range(config.iterations + hybrid):
        kept = explained_matches(pose, T_wi, matches, camera, config.epipolar_px)
        pixels, points = reference_points(T_wi, kept, camera, config.reprojection_px, config.min_angle_deg)
        if step == config.iterations:  # every resection stood: the hybrid step from the last one
            return Resection(_hybrid(pose, T_wi, kept, pixels, points, intrinsics, config), result.n_inliers)
        if len(points) < config.min_inliers:
            return result
        found, info = poselib.estimate_absolute_pose(
            pixels, points, intrinsics, {"max_reproj_error": config.reprojection_px}, {}
        )
        if info["num_inliers"] < config.min_inliers:
            return result
        pose = invert_pose(make_pose(found.R, found.t))
        result = Resection(pose, int(info["num_inliers"]))
    return result


def _camera_pose(T_cw: NDArray[np.float64]) -> poselib.CameraPose:
    """poselib's pose of a world -> camera transform (4, 4)."""
    pose = poselib.CameraPose()
    pose.R, pose.t = T_cw[:3, :3], T_cw[:3, 3]
    return pose


def _hybrid(
    T_wq: NDArray[np.float64],
    T_wi: NDArray[np.float64],
    kept: list[NDArray[np.float64]],
    pixels: NDArray[np.float64],
    points: NDArray[np.float64],
    intrinsics: dict,
    config: ResectionConfig,
) -> NDArray[np.float64]:
    """The hybrid step (module docstring) from the resected pose ``T_wq`` over the matches it
    explains (``kept``, per reference) and their triangulated ``points`` seen at query ``pixels``:
    points at ``reprojection_px``, single matches at ``hybrid_epipolar_px``."""
    pairs = []
    for i, m in enumerate(kept):
        if len(m):
            pair = poselib.PairwiseMatches()
            pair.cam_id1, pair.cam_id2 = i, 0
            pair.x1, pair.x2 = np.ascontiguousarray(m[:, 2:]), np.ascontiguousarray(m[:, :2])
            pairs.append(pair)
    found, _ = poselib.estimate_hybrid_pose(
        pixels,
        points,
        pairs,
        intrinsics,
        [_camera_pose(T) for T in invert_pose(T_wi)],
        [intrinsics] * len(T_wi),
        {"max_reproj_error": config.reprojection_px, "max_epipolar_error": config.hybrid_epipolar_px},
        {},
        _camera_pose(invert_pose(T_wq)),
    )
    T = invert_pose(make_pose(found.R, found.t))
    return T if np.isfinite(T).all() else T_wq
