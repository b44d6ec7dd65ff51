"""Support: how many of the query's feature matches with each reference a pose explains.

Poses are ``T_wq`` / ``T_wi`` (OpenCV camera -> world, metres); matches are per reference (m_i, 4)
pixels ``(u_q, v_q, u_i, v_i)`` (:attr:`BackboneOutput.matches`). The query's pairs a pose is
checked against travel together as one :class:`Pairs` value.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from vgpnav_env.geometry import PinholeCamera, invert_pose, make_pose, rotation_angle
from vgpnav_env.perception.backbones.base import BackboneOutput
from vgpnav_env.perception.backbones.classical import (
    dominant_plane,
    in_front_of_both,
    sampson_distance,
    triangulate_query_depth,
)
from vgpnav_env.perception.verify.config import VerifyConfig


@dataclass(frozen=True, eq=False)
class Pairs:
    """The query's pairs with its references that a pose is checked against: the references' poses
    ``T_wi`` (k, 4, 4), the backbone output ``out`` of the query with exactly these references, the
    ``camera`` and the verification settings ``config``. Immutable; compared by identity (it holds
    arrays), and its :attr:`own` support is computed once."""

    T_wi: NDArray[np.float64]
    out: BackboneOutput
    camera: PinholeCamera
    config: VerifyConfig

    @cached_property
    def own(self) -> NDArray[np.int64]:
        """(k,) the pairs' own support (:func:`pair_support`), computed once per value."""
        return pair_support(self)


def epipolar_support(
    T_wq: NDArray[np.float64],
    T_wi: NDArray[np.float64],
    matches: Sequence[NDArray[np.floating]],
    camera: PinholeCamera,
    max_error_px: float,
) -> NDArray[np.int64]:
    """How many of each reference's feature matches the pose ``T_wq`` explains: (k,) counts.

    ``T_wi`` (k, 4, 4): the references' poses; ``matches``: per reference (m_i, 4) pixels
    ``(u_q, v_q, u_i, v_i)`` (:attr:`BackboneOutput.matches`). Under the relative pose
    ``T_iq = T_wi^-1 T_wq`` a match counts when its Sampson distance to the epipolar geometry is
    below ``max_error_px`` (pixels, at the camera's focal length) and its triangulated point lies
    in front of both cameras; a reference at the query's centre (under 1 mm) is a pure rotation
    and its matches are checked by reprojection. This
    uses nothing of how the pose was found (retrieval, motion averaging), so it checks any pose
    hypothesis against any references the query was matched with. ``T_wq`` may stack P poses
    (P, 4, 4): the counts are then (P, k), one row per pose.
    """
    T_wq = np.asarray(T_wq, float)
    poses = T_wq.reshape(-1, 4, 4)
    out = np.zeros((len(poses), len(matches)), np.int64)
    for i, err in enumerate(match_errors(poses, T_wi, matches, camera)):
        out[:, i] = np.count_nonzero(err < max_error_px, axis=1)
    return out if T_wq.ndim == 3 else out[0]


def explained_matches(
    T_wq: NDArray[np.float64],
    T_wi: NDArray[np.float64],
    matches: Sequence[NDArray[np.floating]],
    camera: PinholeCamera,
    max_error_px: float,
) -> list[NDArray[np.float64]]:
    """Per reference, the matches (m, 4) pixels that one pose ``T_wq`` explains, as
    :func:`epipolar_support` counts them."""
    errors = match_errors(np.asarray(T_wq, float)[None], T_wi, matches, camera)
    arrays = [np.asarray(m, float).reshape(-1, 4) for m in matches]
    return [m[e[0] < max_error_px] for m, e in zip(arrays, errors, strict=True)]


def match_errors(
    T_wq: NDArray[np.float64],
    T_wi: NDArray[np.float64],
    matches: Sequence[NDArray[np.floating]],
    camera: PinholeCamera,
) -> list[NDArray[np.float64]]:
    """Per reference, the errors (P, m_i) in pixels of its matches under each of P poses ``T_wq``
    (P, 4, 4): :func:`epipolar_support`'s Sampson distance (inf behind a camera or undefined)."""
    T_wi = np.asarray(T_wi, float).reshape(-1, 4, 4)
    if len(matches) != len(T_wi):
        raise ValueError(f"got {len(matches)} match arrays for {len(T_wi)} reference poses")
    K_inv = np.linalg.inv(camera.K)
    f = float(np.sqrt(camera.K[0, 0] * camera.K[1, 1]))
    errors = []
    for T, m in zip(T_wi, matches, strict=True):
        m = np.asarray(m, float).reshape(-1, 4)
        if len(m) == 0:
            errors.append(np.zeros((len(T_wq), 0)))
            continue
        x_q = np.c_[m[:, :2], np.ones(len(m))] @ K_inv.T
        x_i = np.c_[m[:, 2:], np.ones(len(m))] @ K_inv.T
        if len(T_wq) == 1:
            err = f * _pose_errors(invert_pose(T) @ T_wq[0], x_q, x_i)[None]
        else:
            err = f * _pose_errors_many(invert_pose(T) @ T_wq, x_q, x_i)
        errors.append(np.nan_to_num(err, nan=np.inf))
    return errors


def _pose_errors(
    T_iq: NDArray[np.float64], x_q: NDArray[np.float64], x_i: NDArray[np.float64]
) -> NDArray[np.float64]:
    """(m,) errors (normalised units) of normalised ray pairs (m, 3) under one relative pose
    ``T_iq``: Sampson distance, inf behind a camera; reprojection for a pure rotation."""
    R, t = T_iq[:3, :3], T_iq[:3, 3]
    if np.linalg.norm(t) < 1e-3:
        Rx = x_q @ R.T
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.linalg.norm(Rx[:, :2] / Rx[:, 2:3] - x_i[:, :2], axis=1)
    err = sampson_distance(x_q, x_i, R, t)
    err[~triangulate_query_depth(x_q, x_i, R, t)[2]] = np.inf
    return err


def _pose_errors_many(
    T_iq: NDArray[np.float64], x_q: NDArray[np.float64], x_i: NDArray[np.float64]
) -> NDArray[np.float64]:
    """(P, m) :func:`_pose_errors` of P relative poses ``T_iq`` (P, 4, 4) at once."""
    R, t = T_iq[:, :3, :3], T_iq[:, :3, 3]
    err = sampson_distance(x_q, x_i, R, t)
    err[~in_front_of_both(x_q, x_i, R, t)] = np.inf
    still = np.linalg.norm(t, axis=1) < 1e-3
    for p in np.flatnonzero(still):
        err[p] = _pose_errors(T_iq[p], x_q, x_i)
    return err


def off_plane_matches(out: BackboneOutput, threshold_px: float) -> BackboneOutput:
    """``out`` with each reference's ``matches`` reduced to those off the pair's dominant plane: the
    matches that the homography RANSAC (OpenCV, ``threshold_px`` pixels) fits to most of them does
    not explain. A pair under 8 matches keeps none. Without matches, ``out`` unchanged."""
    if out.matches is None:
        return out
    kept = []
    for m in out.matches:
        m = np.asarray(m, np.float32).reshape(-1, 4)
        if len(m) < 8:
            kept.append(m[:0])
            continue
        kept.append(m[~dominant_plane(m[:, :2], m[:, 2:], threshold_px)])
    return replace(out, matches=kept)


def reference_support(T_wq: NDArray[np.float64], pairs: Pairs) -> NDArray[np.int64]:
    """(k,) matches of each reference that the pose ``T_wq`` explains: :func:`epipolar_support` of
    the backbone's ``matches``; a backbone without matches (``matches`` None) counts a pair's
    ``n_matches`` when its own relative pose agrees with ``T_wq`` (rotation and direction of the
    query centre seen from the reference within ``rival_angle_deg``), else 0. ``T_wq`` may stack
    P poses (P, 4, 4): (P, k), one row per pose."""
    T_wi, out, config = pairs.T_wi, pairs.out, pairs.config
    if out.matches is not None:
        return epipolar_support(T_wq, T_wi, out.matches, pairs.camera, config.max_epipolar_error_px)
    if np.ndim(T_wq) == 3:
        return np.stack([reference_support(T, pairs) for T in T_wq]).reshape(len(T_wq), len(T_wi))
    T_iq_pose = invert_pose(T_wi) @ T_wq
    T_iq = out.T_iq
    limit = np.deg2rad(config.rival_angle_deg)
    agree = np.zeros(len(T_wi), bool)
    for i in range(len(T_wi)):
        if out.confidence[i] <= 0:
            continue
        a, b = T_iq_pose[i, :3, 3], T_iq[i, :3, 3]
        cos = float(a @ b) / max(float(np.linalg.norm(a) * np.linalg.norm(b)), 1e-12)
        same_direction = np.arccos(np.clip(cos, -1.0, 1.0)) <= limit
        agree[i] = rotation_angle(T_iq_pose[i, :3, :3], T_iq[i, :3, :3]) <= limit and same_direction
    return np.where(agree, out.n_matches, 0).astype(np.int64)


def pair_support(pairs: Pairs) -> NDArray[np.int64]:
    """(k,) matches of each pair that the pair's own relative pose ``T_iq`` explains (the query
    where that pair alone puts it, :func:`epipolar_support`); a backbone without matches: its
    ``n_matches``. Pairs without confidence count 0. Cached as :attr:`Pairs.own`."""
    T_wi, out = pairs.T_wi, pairs.out
    if out.matches is None:
        return np.where(out.confidence > 0, out.n_matches, 0).astype(np.int64)
    own = np.zeros(len(T_wi), np.int64)
    error_px = pairs.config.max_epipolar_error_px
    for i in np.flatnonzero(out.confidence > 0):
        T = T_wi[i] @ out.T_iq[i]
        own[i] = epipolar_support(T, T_wi[i][None], [out.matches[i]], pairs.camera, error_px)[0]
    return own


def explained_confidence(
    T_wq: NDArray[np.float64], pairs: Pairs, support: NDArray[np.int64] | None = None
) -> float:
    """The share in [0, 1] of the backbone's pair confidence that the pose ``T_wq`` explains:
    ``sum_i c_i min(1, s_i / o_i) / sum_i c_i`` over the pairs with confidence ``c_i > 0``, where
    ``s_i`` counts the matches of pair i the pose explains (:func:`reference_support`; ``support``
    when already computed) and ``o_i`` those the pair's own relative pose ``T_iq`` explains
    (:attr:`Pairs.own`). 0 when no pair has confidence.
    """
    c = np.asarray(pairs.out.confidence, float)
    idx = np.flatnonzero(c > 0)
    if len(idx) == 0:
        return 0.0
    s = reference_support(T_wq, pairs) if support is None else np.asarray(support)
    own = np.asarray(pairs.own)[idx]
    share = np.minimum(s[idx] / np.maximum(own, 1.0), 1.0)
    return float((c[idx] * share).sum() / c[idx].sum())


def refine_pose(
    T_wq: NDArray[np.float64],
    pairs: Pairs,
    *,
    max_shift: float,
    max_height: float = 0.05,
    max_rotation_deg: float = 1.5,
) -> NDArray[np.float64]:
    """``T_wq`` moved to the pose whose epipolar geometry with the references ``pairs.T_wi`` best
    explains their matches (:attr:`BackboneOutput.matches`, which ``pairs.out`` must have):
    robust (Cauchy, ``max_epipolar_error_px``) least squares of the Sampson distances over all
    references at once, rotation and metric position (the references' known poses fix the scale),
    within ``max_rotation_deg`` about each axis, ``max_shift`` metres horizontally and
    ``max_height`` vertically of ``T_wq`` (a pose refined freely can slide to a wrong one that a
    repeated texture supports as well).
    A pose a few centimetres or a degree off explains few of the matches within
    ``max_epipolar_error_px``; refined, the references that see the place explain it. Returns
    ``T_wq`` unchanged when fewer than 8 matches are given."""
    T_wi, matches, camera, config = pairs.T_wi, pairs.out.matches, pairs.camera, pairs.config
    m = [np.asarray(a, float).reshape(-1, 4) for a in matches]
    ref = np.concatenate([np.full(len(a), i) for i, a in enumerate(m)]).astype(int)
    if len(ref) < 8:
        return T_wq
    uv = np.concatenate(m)
    K_inv = np.linalg.inv(camera.K)
    f = float(np.sqrt(camera.K[0, 0] * camera.K[1, 1]))
    x_q = np.c_[uv[:, :2], np.ones(len(uv))] @ K_inv.T
    x_i = np.c_[uv[:, 2:], np.ones(len(uv))] @ K_inv.T
    R_iw = np.transpose(T_wi[:, :3, :3], (0, 2, 1))
    R0 = T_wq[:3, :3]

    def pose(p: NDArray[np.float64]) -> NDArray[np.float64]:
        return make_pose(R0 @ Rotation.from_rotvec(p[:3]).as_matrix(), p[3:])

    def residuals(p: NDArray[np.float64]) -> NDArray[np.float64]:
        T = pose(p)
        R = R_iw @ T[:3, :3]  # (k, 3, 3) R_iq
        t = np.einsum("kij,kj->ki", R_iw, T[:3, 3] - T_wi[:, :3, 3])
        t = t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-9)
        tx = np.zeros((len(t), 3, 3))
        tx[:, 0, 1], tx[:, 0, 2], tx[:, 1, 2] = -t[:, 2], t[:, 1], -t[:, 0]
        tx[:, 1, 0], tx[:, 2, 0], tx[:, 2, 1] = t[:, 2], -t[:, 1], t[:, 0]
        E = (tx @ R)[ref]
        Ex_q = np.einsum("mij,mj->mi", E, x_q)
        Etx_i = np.einsum("mji,mj->mi", E, x_i)
        num = np.einsum("mi,mi->m", x_i, Ex_q)
        den = Ex_q[:, 0] ** 2 + Ex_q[:, 1] ** 2 + Etx_i[:, 0] ** 2 + Etx_i[:, 1] ** 2
        return f * num / np.sqrt(np.maximum(den, 1e-18))

    p0 = np.r_[np.zeros(3), T_wq[:3, 3]]
    step = np.r_[np.full(3, np.deg2rad(max_rotation_deg)), max_shift, max_shift, max_height]
    fit = least_squares(
        residuals,
        p0,
        bounds=(p0 - step, p0 + step),
        loss="cauchy",
        f_scale=config.max_epipolar_error_px,
        max_nfev=50,
    )
    return pose(fit.x)
