"""Weighted motion averaging: the metric query pose from k references and a backbone's relative poses.

Inputs per reference i: ``T_wi`` (reference camera -> world, metric), ``T_qi`` (reference
camera -> query camera, from the backbone: rotation exact up to noise, translation at one
unknown common scale) and a backbone confidence in [0, 1]. Derived:

- ``R_iq = R_qi^T``, ``t_iq = -R_iq t_qi`` (query centre in reference frame i, backbone units);
- rotation hypothesis ``R_wq^(i) = R_wi R_iq``;
- world ray ``c_i + s v_i`` (s > 0) through the query centre, ``c_i = t_wi``,
  ``v_i = R_wi t_iq / |t_iq|``.

Rotation: consensus by mutual angular consistency (the seed: the hypothesis whose agreeing
hypotheses, at least ``min_consensus`` of them, have the largest total confidence),
Gaussian-kernel weights times confidence, weighted quaternion mean. Translation: IRLS triangulation
``min_t sum_i Omega_i |(I - v_i v_i^T)(t - c_i)|^2``, ``Omega_i = w_rot w_geo w_res``.
Once stage 4 has the metric scale, :func:`metric_centre` re-solves the centre with each pair's
metric distance along its ray too: rays that are nearly parallel (references in a line with the
query) fix the centre across them but not along them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from vgpnav_env.geometry import invert_pose, make_pose

#: Motion-averaging methods: weighted over all references, or one reference (ablation).
AVERAGING_METHODS = ("weighted", "single")


@dataclass(frozen=True)
class MotionAveragingConfig:
    """Motion-averaging settings (angles in degrees, lengths in metres).

    ``method="single"`` (ablation) takes the pose from one reference (``single_reference``:
    ``"first"`` = the first given, i.e. the best retrieval match; ``"confidence"`` = the most
    confident) and needs a scale for its translation (see :func:`average_motion`).
    ``distance_sigma``: the relative noise of a pair's metric distance (the scale times its
    backbone translation) against a ray's angular noise of ``rotation_sigma_deg``, both growing
    with the distance (:func:`metric_centre`; None: the rays alone place the centre).
    """

    method: Literal["weighted", "single"] = "weighted"
    consensus_deg: float = 5.0
    rotation_sigma_deg: float = 3.0
    min_consensus: int = 2
    irls_iterations: int = 10
    robust_loss: Literal["cauchy", "huber"] = "cauchy"
    robust_scale_m: float = 0.05
    inlier_residual_m: float = 0.3
    min_rays: int = 2
    min_ray_angle_deg: float = 2.0
    single_reference: Literal["first", "confidence"] = "first"
    distance_sigma: float | None = 0.1

    def __post_init__(self) -> None:
        if self.method not in AVERAGING_METHODS:
            raise ValueError(f"method must be one of {AVERAGING_METHODS}, got {self.method!r}")
        if self.robust_loss not in ("cauchy", "huber"):
            raise ValueError(f"robust_loss must be 'cauchy' or 'huber', got {self.robust_loss!r}")
        if self.single_reference not in ("first", "confidence"):
            raise ValueError(
                f"single_reference must be 'first' or 'confidence', got {self.single_reference!r}"
            )
        if min(self.consensus_deg, self.rotation_sigma_deg, self.robust_scale_m, self.inlier_residual_m) <= 0:
            raise ValueError(
                "consensus_deg, rotation_sigma_deg, robust_scale_m, inlier_residual_m must be > 0"
            )
        if self.distance_sigma is not None and not self.distance_sigma > 0:
            raise ValueError(f"distance_sigma must be > 0 or None, got {self.distance_sigma}")
        if self.min_rays < 2 or self.min_consensus < 1 or self.irls_iterations < 1:
            raise ValueError("need min_rays >= 2, min_consensus >= 1 and irls_iterations >= 1")


@dataclass
class MotionResult:
    """Outcome of motion averaging.

    ``T_wq``: metric query pose (identity with ``ok=False`` when nothing could be estimated).
    ``weights`` (k,): final translation weights Omega_i (0 for rejected references).
    ``inliers`` (k,): references agreeing in rotation, in front (s > 0) and within
    ``inlier_residual_m`` of the solution. ``consensus``: size of the rotation consensus.
    ``ray_depths`` (k,): metric distance s_i along each ray to the query centre (nan if
    unused). ``scale_from_rays``: weighted median of s_i / |t_iq| over inliers = metres per
    backbone unit implied by the triangulation (nan if unavailable); a cross-check for the
    ground-anchored scale.
    """

    T_wq: NDArray[np.float64]
    weights: NDArray[np.float64]
    inliers: NDArray[np.bool_]
    consensus: int
    ok: bool
    reason: str = ""
    rotation_weights: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    ray_depths: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    scale_from_rays: float = float("nan")


def _robust_weights(r: NDArray[np.float64], scale: float, loss: str) -> NDArray[np.float64]:
    if loss == "huber":
        return np.where(r <= scale, 1.0, scale / np.maximum(r, 1e-12))
    return 1.0 / (1.0 + (r / scale) ** 2)


def _robust_cost(r: NDArray[np.float64], scale: float, loss: str) -> NDArray[np.float64]:
    if loss == "huber":
        return np.where(r <= scale, 0.5 * r**2, scale * (r - 0.5 * scale))
    return 0.5 * scale**2 * np.log1p((r / scale) ** 2)


def _weighted_median(x: NDArray[np.float64], w: NDArray[np.float64]) -> float:
    o = np.argsort(x)
    cw = np.cumsum(w[o])
    return float(x[o][np.searchsorted(cw, 0.5 * cw[-1])])


def pair_centre(T_wi: ArrayLike, T_iq: ArrayLike, scale: float) -> NDArray[np.float64]:
    """World centre of the query placed by one pair: the reference centre ``c_i`` plus the pair's
    translation ``t_iq`` (backbone units) at ``scale`` metres per unit, rotated into W."""
    T_wi, T_iq = np.asarray(T_wi, float), np.asarray(T_iq, float)
    return T_wi[:3, 3] + scale * T_wi[:3, :3] @ T_iq[:3, 3]


def ray_residuals(
    t: ArrayLike, centres: NDArray[np.float64], dirs: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Signed distances s_i (n,) of ``t`` along unit rays (n, 3) and its distances to their lines."""
    d = np.asarray(t, float) - centres
    s = np.einsum("ij,ij->i", d, dirs)
    perp = d - s[:, None] * dirs
    return s, np.linalg.norm(perp, axis=1)


def triangulate_rays(
    centres: NDArray[np.float64], dirs: NDArray[np.float64], weights: NDArray[np.float64]
) -> tuple[NDArray[np.float64], float]:
    """Weighted least-squares point closest to lines ``c_i + s v_i`` and the conditioning.

    Returns the point and the smallest eigenvalue of ``sum w_i (I - v_i v_i^T) / sum w_i``
    (sin^2(theta/2) for two equally weighted rays at angle theta; 0 for parallel rays).
    """
    w = np.asarray(weights, float)
    P = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]
    A = np.einsum("i,ijk->jk", w, P)
    b = np.einsum("i,ijk,ik->j", w, P, centres)
    total = w.sum()
    if total <= 0:
        return np.full(3, np.nan), 0.0
    cond = float(np.linalg.eigvalsh(A / total)[0])
    if cond < 1e-12:
        return np.full(3, np.nan), cond
    return np.linalg.solve(A, b), cond


def _pairwise_midpoints(
    centres: NDArray[np.float64], dirs: NDArray[np.float64], min_angle: float
) -> NDArray[np.float64]:
    """Midpoints (m, 3) of the closest points of every pair of rays that meet in front of both."""
    a, b = np.triu_indices(len(centres), 1)
    cos = np.einsum("ij,ij->i", dirs[a], dirs[b])
    w0 = centres[a] - centres[b]
    d = np.einsum("ij,ij->i", dirs[a], w0)
    e = np.einsum("ij,ij->i", dirs[b], w0)
    denom = 1.0 - cos**2
    ok = denom > np.sin(min_angle) ** 2
    denom = np.where(ok, denom, 1.0)
    s = (cos * e - d) / denom
    u = (e - cos * d) / denom
    ok &= (s > 0) & (u > 0)
    mid = 0.5 * (centres[a] + s[:, None] * dirs[a] + centres[b] + u[:, None] * dirs[b])
    return mid[ok]


def _rotation_consensus(
    quats: NDArray[np.float64],
    confidence: NDArray[np.float64],
    valid: NDArray[np.bool_],
    config: MotionAveragingConfig,
) -> tuple[Rotation, NDArray[np.float64], NDArray[np.bool_], int]:
    """Consensus rotation, per-hypothesis deviation (rad), inlier mask and consensus size."""
    thr = np.deg2rad(config.consensus_deg)
    pair_angle = 2.0 * np.arccos(np.clip(np.abs(quats @ quats.T), 0.0, 1.0))
    pair_angle[~valid, :] = np.inf
    pair_angle[:, ~valid] = np.inf
    agree = pair_angle <= thr
    support = agree.sum(axis=1)
    # A seed with enough agreeing hypotheses first, then the most confident agreement (a cluster
    # of weak, mutually consistent pairs -- a repeated texture -- loses to fewer strong ones).
    weighted_support = agree.astype(float) @ confidence
    seed = int(np.lexsort((-weighted_support, support < config.min_consensus))[0])
    members = pair_angle[seed] <= thr
    # Sign-align the members to the seed and take their confidence-weighted mean.
    aligned = quats * np.where(quats @ quats[seed] < 0, -1.0, 1.0)[:, None]
    w = np.maximum(confidence, 1e-6) * members
    R_c = Rotation.from_quat(aligned[members]).mean(weights=w[members])
    dev = (Rotation.from_quat(quats) * R_c.inv()).magnitude()
    inliers = valid & (dev <= thr)
    return R_c, dev, inliers, int(members.sum())


def average_motion(
    T_wi: ArrayLike,
    T_qi: ArrayLike,
    confidence: ArrayLike,
    config: MotionAveragingConfig | None = None,
    *,
    single_scale: float = 1.0,
    scale_valid: ArrayLike | None = None,
) -> MotionResult:
    """Metric pose ``T_wq`` of the query camera from k references (see module docstring).

    ``T_wi``, ``T_qi``: (k, 4, 4); ``confidence``: (k,) in [0, 1], references with confidence
    0 or non-finite poses are ignored. ``scale_valid`` (k,) marks the pairs whose translation
    length shares the common scale (``BackboneOutput.scale_valid``); only they enter
    ``scale_from_rays`` (directions of all pairs are used). With
    ``config.method="single"`` the pose comes from one reference and its position is
    ``c_i + single_scale * R_wi t_iq``: ``single_scale`` converts backbone units to metres;
    the default 1.0 keeps backbone units, which is what makes this ablation poor unless the
    caller supplies a scale. Never raises on bad geometry: returns ``ok=False`` + ``reason``.
    """
    config = config or MotionAveragingConfig()
    T_wi = np.asarray(T_wi, float)
    T_qi = np.asarray(T_qi, float)
    conf = np.asarray(confidence, float)
    k = len(conf)
    if conf.ndim != 1 or T_wi.shape != (k, 4, 4) or T_qi.shape != (k, 4, 4):
        raise ValueError(
            f"need T_wi (k,4,4), T_qi (k,4,4), confidence (k,); got {T_wi.shape}, {T_qi.shape}, {conf.shape}"
        )
    zeros = np.zeros(k)
    fail = MotionResult(np.eye(4), zeros, np.zeros(k, bool), 0, False, "", zeros.copy(), np.full(k, np.nan))
    sv = np.ones(k, bool) if scale_valid is None else np.asarray(scale_valid, bool)
    if sv.shape != (k,):
        raise ValueError(f"scale_valid must have shape ({k},), got {sv.shape}")
    finite = np.isfinite(T_wi).all(axis=(1, 2)) & np.isfinite(T_qi).all(axis=(1, 2)) & np.isfinite(conf)
    conf = np.where(finite, np.clip(np.nan_to_num(conf), 0.0, 1.0), 0.0)
    finite &= conf > 0
    if k == 0 or not finite.any():
        fail.reason = "too few references"
        return fail

    T_iq = invert_pose(np.where(finite[:, None, None], T_qi, np.eye(4)))
    R_wi, c = T_wi[:, :3, :3], T_wi[:, :3, 3]
    R_hyp = np.einsum("kij,kjl->kil", R_wi, T_iq[:, :3, :3])
    t_iq = T_iq[:, :3, 3]
    baseline = np.linalg.norm(t_iq, axis=1)

    if config.method == "single":
        usable = np.flatnonzero(finite)
        i = int(usable[0] if config.single_reference == "first" else usable[np.argmax(conf[usable])])
        T = make_pose(R_hyp[i], pair_centre(T_wi[i], T_iq[i], single_scale))
        w = np.zeros(k)
        w[i] = 1.0
        mask = w > 0
        return MotionResult(
            T, w, mask, 1, True, "single reference", w.copy(), np.where(mask, single_scale * baseline, np.nan)
        )

    quats = Rotation.from_matrix(np.where(finite[:, None, None], R_hyp, np.eye(3))).as_quat()
    R_c, dev, rot_inl, consensus = _rotation_consensus(quats, conf, finite, config)
    fail.consensus = consensus
    if consensus < config.min_consensus:
        fail.reason = "no consensus"
        return fail
    sigma = np.deg2rad(config.rotation_sigma_deg)
    w_rot = np.exp(-0.5 * (dev / sigma) ** 2) * np.maximum(conf, 1e-6) * rot_inl
    R_wq = Rotation.from_matrix(R_hyp[rot_inl]).mean(weights=w_rot[rot_inl])
    fail.rotation_weights = w_rot

    has_dir = rot_inl & (baseline > 1e-9 * max(float(baseline.max()), 1e-300))
    if has_dir.sum() < config.min_rays:
        fail.reason = "too few references"
        return fail
    v = np.einsum("kij,kj->ki", R_wi, t_iq / np.maximum(baseline, 1e-300)[:, None])
    active = has_dir.copy()

    def geo_weights(mask: NDArray[np.bool_]) -> NDArray[np.float64]:
        sines = np.linalg.norm(np.cross(v[:, None], v[None]), axis=2)
        n_other = mask.sum() - mask.astype(int)
        return np.where(mask, (sines * mask[None]).sum(1) / np.maximum(n_other, 1), 0.0)

    w_prior = w_rot * geo_weights(active)
    if not np.any(w_prior > 0):
        fail.reason = "degenerate rays"
        return fail

    # Robust initialisation: the best of the pairwise ray intersections and the LS solution.
    candidates = list(_pairwise_midpoints(c[active], v[active], np.deg2rad(config.min_ray_angle_deg)))
    p, _ = triangulate_rays(c[active], v[active], w_prior[active])
    if np.all(np.isfinite(p)):
        candidates.append(p)
    if not candidates:
        fail.reason = "degenerate rays"
        return fail

    # Robust cost of every candidate; a ray pointing away counts its full distance to the centre.
    cand = np.array(candidates)
    diff = cand[:, None, :] - c[active][None]
    along = np.einsum("mkj,kj->mk", diff, v[active])
    r = np.linalg.norm(diff - along[..., None] * v[active][None], axis=2)
    r = np.where(along > 0, r, np.linalg.norm(diff, axis=2))
    cost = _robust_cost(r, config.robust_scale_m, config.robust_loss) @ w_prior[active]
    t = cand[int(np.argmin(cost))]
    min_cond = np.sin(0.5 * np.deg2rad(config.min_ray_angle_deg)) ** 2
    omega = np.zeros(k)
    for _ in range(config.irls_iterations):
        s, r = ray_residuals(t, c, v)
        active = has_dir & (s > 0)
        if active.sum() < config.min_rays:
            break
        w_res = _robust_weights(r, config.robust_scale_m, config.robust_loss)
        omega = np.where(active, w_rot * geo_weights(active) * w_res, 0.0)
        t_new, cond = triangulate_rays(c, v, omega)
        if not np.all(np.isfinite(t_new)) or cond < min_cond:
            fail.reason = "degenerate rays"
            return fail
        converged = np.linalg.norm(t_new - t) < 1e-6
        t = t_new
        if converged:
            break

    s, r = ray_residuals(t, c, v)
    inliers = has_dir & (s > 0) & (r <= config.inlier_residual_m)
    omega = np.where(inliers, omega, 0.0)
    result = MotionResult(
        make_pose(R_wq, t), omega, inliers, consensus, True, "", w_rot, np.where(has_dir, s, np.nan)
    )
    if inliers.sum() < config.min_rays:
        result.ok, result.reason = False, "too few inlier rays"
        return result
    _, cond = triangulate_rays(c[inliers], v[inliers], omega[inliers])
    if cond < min_cond:
        result.ok, result.reason = False, "degenerate rays"
        return result
    scaled = inliers & sv
    if scaled.any():
        result.scale_from_rays = _weighted_median(s[scaled] / baseline[scaled], omega[scaled])
    return result


def metric_centre(
    motion: MotionResult,
    T_wi: ArrayLike,
    T_iq: ArrayLike,
    scale: float,
    scale_valid: ArrayLike,
    config: MotionAveragingConfig | None = None,
) -> NDArray[np.float64]:
    """``motion.T_wq`` with its centre re-solved from the rays and the pairs' metric distances:
    ``min_t sum_i Omega_i (|(I - v_i v_i^T)(t - c_i)|^2 + lam (v_i^T (t - c_i) - d_i)^2)`` over the
    references motion averaging kept (``motion.weights`` Omega_i > 0), ``d_i = scale |t_iq|``
    (metres; only pairs marked in ``scale_valid``, the others constrain across their ray alone),
    ``lam = (rotation_sigma_deg in rad / distance_sigma)^2``. ``T_wi`` (k, 4, 4) W <- reference,
    ``T_iq`` (k, 4, 4) query -> reference in backbone units, ``scale`` metres per unit. The
    rotation is kept; ``motion.T_wq`` is returned unchanged when the config has no
    ``distance_sigma``, the scale is not finite and positive, or no kept pair has a distance."""
    config = config or MotionAveragingConfig()
    T_wq = np.asarray(motion.T_wq, float)
    omega = np.asarray(motion.weights, float)
    t_iq = np.asarray(T_iq, float)[:, :3, 3]
    baseline = np.linalg.norm(t_iq, axis=1)
    use = (omega > 0) & (baseline > 0)
    metric = use & np.asarray(scale_valid, bool)
    if config.distance_sigma is None or not (np.isfinite(scale) and scale > 0) or not metric.any():
        return T_wq
    T_wi = np.asarray(T_wi, float)
    c = T_wi[use, :3, 3]
    v = np.einsum("kij,kj->ki", T_wi[use, :3, :3], t_iq[use]) / baseline[use, None]
    w = omega[use]
    lam = np.where(metric[use], (np.deg2rad(config.rotation_sigma_deg) / config.distance_sigma) ** 2, 0.0)
    d = scale * baseline[use]
    outer = v[:, :, None] * v[:, None, :]
    A = np.einsum("i,ijk->jk", w, np.eye(3)[None] - outer + lam[:, None, None] * outer)
    b = np.einsum("i,ijk,ik->j", w, np.eye(3)[None] - outer, c) + np.einsum(
        "i,ij->j", w * lam, v * (np.einsum("ij,ij->i", v, c) + d)[:, None]
    )
    return make_pose(T_wq[:3, :3], np.linalg.solve(A, b))
