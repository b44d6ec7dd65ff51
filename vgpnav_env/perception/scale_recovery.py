"""Ground-anchored scale recovery: metres per backbone unit from the ground plane.

The backbone's query points ``p`` (query camera frame, OpenCV, backbone units) are rotated
into the gravity frame with the metric query rotation ``R_wq``; their heights relative to
the camera are ``h = (R_wq p)_z``. The ground is the dominant peak of the height
distribution below the camera, at ``h_ground_b < 0`` (backbone units). With the ground
height ``z_ground`` anchored in W at initialisation (camera pose minus the calibrated
camera height), each frame's scale is ``(t_wq.z - z_ground) / (-h_ground_b)``.

Recommended use (the query alone misses the ground more often than the whole reconstruction
with a prior): histogram the whole reconstruction (:func:`reconstruction_points`)
and pass ``GroundAnchor.expected_height_b(T_wq, MotionResult.scale_from_rays)`` as the prior.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import gaussian_filter1d

from vgpnav_env.geometry import PinholeCamera, transform_points
from vgpnav_env.perception.points import depth_points


@dataclass(frozen=True)
class ScaleConfig:
    """Scale-recovery settings; ``enabled=False`` is the ablation (scale = 1, backbone units).

    Heights are binned with a width of ``bin_fraction`` x the median height below the camera
    (scale-free). A ground peak is a local maximum of the smoothed histogram; its support is
    the weight within ``window_bins`` bins over the weight of all points. A peak's mean
    density must be >= ``min_contrast`` x the mean density within ``wide_factor`` x
    ``window_bins`` bins of it (a wall's even spread of heights is no ground). Among peaks
    with support >= ``min_support`` the lowest one whose support is >= ``relative_peak_support``
    x the dominant peak's is taken (1.0 = strictly the dominant peak; lower values prefer the
    floor over a large table top seen from above: nothing lies below the floor). The search
    runs at bin widths ``levels`` x the base width (depth noise smears the ground peak) and
    keeps the lowest peak found; its height is the weighted median of its window, re-centred
    with the finest bins. ``below_margin``: points lower than the ground by more than this
    fraction of its depth under the camera count as under it (:attr:`GroundEstimate.below`; 0.125
    is 0.15 m at a 1.2 m camera height). ``height_source="pose"`` uses ``t_wq.z - z_ground`` as the metric
    camera height; ``"calibrated"`` uses the calibrated camera height (planar robots).
    """

    enabled: bool = True
    bin_fraction: float = 0.01
    smooth_bins: float = 1.5
    window_bins: int = 3
    min_support: float = 0.05
    min_points: int = 50
    relative_peak_support: float = 0.3
    min_contrast: float = 1.8
    wide_factor: int = 10
    levels: tuple[int, ...] = (1, 2, 4)
    prior_tolerance: float = 0.25
    prior_min_support: float = 0.02
    below_margin: float = 0.125
    height_source: Literal["pose", "calibrated"] = "pose"

    def __post_init__(self) -> None:
        if not 0 < self.bin_fraction < 1 or self.smooth_bins < 0 or self.window_bins < 0:
            raise ValueError("need 0 < bin_fraction < 1, smooth_bins >= 0 and window_bins >= 0")
        if not 0 <= self.min_support <= 1 or not 0 < self.relative_peak_support <= 1:
            raise ValueError("need min_support in [0, 1] and relative_peak_support in (0, 1]")
        if self.min_contrast < 1 or self.wide_factor < 1:
            raise ValueError("need min_contrast >= 1 and wide_factor >= 1")
        if not self.prior_tolerance > 0 or not 0 <= self.prior_min_support <= 1:
            raise ValueError("need prior_tolerance > 0 and prior_min_support in [0, 1]")
        if self.below_margin < 0:
            raise ValueError(f"below_margin must be >= 0, got {self.below_margin}")
        if not self.levels or min(self.levels) < 1:
            raise ValueError(f"levels must be non-empty integers >= 1, got {self.levels}")
        if self.height_source not in ("pose", "calibrated"):
            raise ValueError(f"height_source must be 'pose' or 'calibrated', got {self.height_source!r}")


@dataclass(frozen=True)
class GroundEstimate:
    """Ground height below the camera in backbone units (< 0), its weight fraction, and success.

    ``below``: the weight fraction of the points more than ``ScaleConfig.below_margin`` x the
    ground's depth under it (0 when not found); nothing lies under a true floor.
    """

    height_b: float
    support: float
    found: bool
    below: float = 0.0


@dataclass(frozen=True)
class ScaleEstimate:
    """Metres per backbone unit and where it came from: ground | fallback | disabled | none."""

    scale: float
    source: Literal["ground", "fallback", "disabled", "none"]

    @property
    def ok(self) -> bool:
        return self.source != "none"


def _weighted_median(x: NDArray[np.float64], w: NDArray[np.float64]) -> float:
    o = np.argsort(x)
    cw = np.cumsum(w[o])
    return float(x[o][np.searchsorted(cw, 0.5 * cw[-1])])


def ground_peak(
    points_q: ArrayLike,
    R_wq: ArrayLike,
    weights: ArrayLike | None = None,
    config: ScaleConfig | None = None,
    prior_height_b: float | None = None,
) -> GroundEstimate:
    """Ground height (backbone units, < 0) below the camera from query points (N, 3) or (H, W, 3).

    ``points_q`` are in the query camera frame -- the query's own points or the whole
    reconstruction (see :func:`reconstruction_points`; references widen the view of the
    ground); ``R_wq`` (3x3) rotates them into the gravity frame (z up); ``weights`` (same
    leading shape, >= 0, e.g. depth confidence) weight the histogram. Non-finite points and
    zero weights are ignored. ``prior_height_b`` (< 0, e.g. from
    :meth:`GroundAnchor.expected_height_b`) restricts the ground to peaks within
    ``config.prior_tolerance`` (relative) of it; the relative-support rule is then dropped
    and ``config.prior_min_support`` replaces ``min_support``.
    """
    config = config or ScaleConfig()
    P = np.asarray(points_q, float).reshape(-1, 3)
    w = np.ones(len(P)) if weights is None else np.asarray(weights, float).reshape(-1)
    if len(w) != len(P):
        raise ValueError(f"weights have {len(w)} entries for {len(P)} points")
    none = GroundEstimate(float("nan"), 0.0, False)
    h = P @ np.asarray(R_wq, float)[2]
    valid = np.isfinite(h) & np.isfinite(w) & (w > 0)
    total = float(w[valid].sum())
    below = valid & (h < 0)
    if below.sum() < config.min_points or total <= 0:
        return none
    hb, wb = h[below], w[below]
    median_depth = float(np.median(-hb))
    best: tuple[float, float, float, float] | None = None  # (lo edge, hi edge, support, centre)
    if prior_height_b is not None and not (np.isfinite(prior_height_b) and prior_height_b < 0):
        raise ValueError(f"prior_height_b must be a negative number or None, got {prior_height_b}")
    for level in config.levels:
        width = level * config.bin_fraction * median_depth
        found = _lowest_peak(hb, wb, total, width, config, prior_height_b)
        # A coarser level only wins with a peak below the finer one's window.
        if found is not None and (best is None or found[3] < best[0]):
            best = found
    if best is None:
        return none
    lo_edge, hi_edge, support, _ = best
    sel = (hb >= lo_edge) & (hb <= hi_edge)
    if sel.sum() < config.min_points:
        return GroundEstimate(float("nan"), support, False)
    height = _weighted_median(hb[sel], wb[sel])
    # Re-centre at the finest bin width: median of the points near the current estimate.
    half = (config.window_bins + 0.5) * config.bin_fraction * median_depth
    for _ in range(3):
        near = np.abs(hb - height) <= half
        if near.sum() < config.min_points:
            break
        height = _weighted_median(hb[near], wb[near])
    under = float(wb[hb < height * (1.0 + config.below_margin)].sum()) / total
    return GroundEstimate(height, support, True, under)


def _lowest_peak(
    hb: NDArray[np.float64],
    wb: NDArray[np.float64],
    total: float,
    width: float,
    config: ScaleConfig,
    prior_height_b: float | None,
) -> tuple[float, float, float, float] | None:
    """Window (lo, hi edges), support and centre of the lowest qualifying histogram peak, or None."""
    lo = float(hb.min())
    n_bins = int(np.ceil(-lo / width)) + 1
    if n_bins > 100_000:  # a few far outliers: bound the histogram to the bulk of the data
        lo = float(np.percentile(hb, 0.5))
        n_bins = int(np.ceil(-lo / width)) + 1
    hist, edges = np.histogram(hb, bins=n_bins, range=(lo, 0.0), weights=wb)
    smooth = gaussian_filter1d(hist, config.smooth_bins, mode="constant") if config.smooth_bins > 0 else hist
    padded = np.concatenate([[-np.inf], smooth, [-np.inf]])
    peaks = np.flatnonzero((smooth >= padded[:-2]) & (smooth > padded[2:]) & (smooth > 0))
    if len(peaks) == 0:
        return None
    csum = np.concatenate([[0.0], np.cumsum(hist)])
    lo_i = np.clip(peaks - config.window_bins, 0, n_bins)
    hi_i = np.clip(peaks + config.window_bins + 1, 0, n_bins)
    support = (csum[hi_i] - csum[lo_i]) / total
    wide = config.wide_factor * config.window_bins
    wlo_i = np.clip(peaks - wide, 0, n_bins)
    whi_i = np.clip(peaks + wide + 1, 0, n_bins)
    density = (csum[hi_i] - csum[lo_i]) / (hi_i - lo_i)
    wide_density = (csum[whi_i] - csum[wlo_i]) / (whi_i - wlo_i)
    contrast = density / np.maximum(wide_density, 1e-300)
    ok = contrast >= config.min_contrast
    centres = 0.5 * (edges[peaks] + edges[peaks + 1])
    if prior_height_b is not None:
        ok &= np.abs(centres / prior_height_b - 1.0) <= config.prior_tolerance
        ok &= support >= config.prior_min_support
    else:
        dominant = float(support[ok].max()) if ok.any() else 0.0
        ok &= support >= max(config.min_support, config.relative_peak_support * dominant)
    if not ok.any():
        return None
    j = int(np.flatnonzero(ok)[0])  # peaks are sorted by height: the lowest qualifying one
    return float(edges[lo_i[j]]), float(edges[hi_i[j]]), float(support[j]), float(centres[j])


def reconstruction_points(
    camera: PinholeCamera,
    query_depth: ArrayLike,
    query_confidence: ArrayLike | None = None,
    T_qi: ArrayLike | None = None,
    reference_depths: ArrayLike | None = None,
    reference_weights: ArrayLike | None = None,
    stride: int = 2,
    reference_stride: int = 4,
    min_confidence: float = 0.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Backbone points (N, 3) in the QUERY camera frame and their weights (N,).

    The query's z-depth (H, W) (0 / non-finite = unknown) at pixels whose ``query_confidence``
    is at least ``min_confidence``, weighted by that confidence, plus, when given, each
    reference's depth (k, H, W) moved into the query frame with ``T_qi`` (k, 4, 4) and weighted
    by ``reference_weights`` (k,) (e.g. the backbone confidence, 0 for pairs off the common
    scale). Pixels are subsampled by the strides (:func:`~vgpnav_env.perception.points.depth_points`).
    """
    qd = np.asarray(query_depth, float)
    qc = np.ones_like(qd) if query_confidence is None else np.asarray(query_confidence, float)
    size = (camera.height, camera.width)
    if qd.shape != size or qc.shape != qd.shape:
        raise ValueError(f"query depth/confidence must have shape {size}, got {qd.shape}, {qc.shape}")
    query, weight = depth_points(camera, qd, qc, stride=stride, min_confidence=min_confidence)
    points, weights = [query], [weight]
    if reference_depths is not None:
        rd = np.asarray(reference_depths, float)
        T = np.asarray(T_qi, float)
        k = len(rd)
        rw = np.ones(k) if reference_weights is None else np.asarray(reference_weights, float)
        if rd.shape[1:] != qd.shape or T.shape != (k, 4, 4) or rw.shape != (k,):
            raise ValueError(
                f"need reference_depths (k, {qd.shape[0]}, {qd.shape[1]}), T_qi (k, 4, 4) and "
                f"reference_weights (k,); got {rd.shape}, {T.shape}, {rw.shape}"
            )
        for i in np.flatnonzero(rw > 0):
            reference, _ = depth_points(camera, rd[i], stride=reference_stride)
            points.append(transform_points(T[i], reference))
            weights.append(np.full(len(reference), rw[i]))
    return np.concatenate(points), np.concatenate(weights)


def recover_metric_points(points_q_b: ArrayLike, T_wq: ArrayLike, scale: float) -> NDArray[np.float64]:
    """World points (..., 3), metres, from query-frame backbone points: ``T_wq (scale * p)``."""
    return transform_points(T_wq, scale * np.asarray(points_q_b, float))


class GroundAnchor:
    """Per-episode ground anchor and the online scale (see module docstring).

    Call :meth:`initialize` once with frames taken while the robot stands still, then
    :meth:`scale_for` every frame. With ``config.enabled=False`` the scale is always 1
    (backbone units) and the anchor still comes from the calibrated camera height.
    """

    def __init__(self, config: ScaleConfig | None = None) -> None:
        self.config = config or ScaleConfig()
        self.z_ground: float | None = None
        self.camera_height_m: float | None = None
        self.initial_scales: NDArray[np.float64] = np.zeros(0)

    @property
    def initialized(self) -> bool:
        return self.z_ground is not None

    def initialize(
        self, observations: Sequence[tuple[ArrayLike, GroundEstimate | None]], camera_height_m: float
    ) -> None:
        """Anchor ``z_ground = mean(t_wq.z) - camera_height_m`` from (T_wq metric, ground) pairs.

        The ground estimates only give the start-up scales (``initial_scales``, diagnostics).
        """
        if not observations:
            raise ValueError("GroundAnchor.initialize needs at least one (T_wq, ground) observation")
        if camera_height_m <= 0:
            raise ValueError(f"camera_height_m must be positive metres, got {camera_height_m}")
        z = np.array([np.asarray(T, float)[2, 3] for T, _ in observations])
        if not np.all(np.isfinite(z)):
            raise ValueError("initialisation poses must be finite")
        self.camera_height_m = float(camera_height_m)
        self.z_ground = float(z.mean()) - self.camera_height_m
        self.initial_scales = np.array(
            [camera_height_m / -g.height_b for _, g in observations if g is not None and g.found]
        )

    def camera_height(self, T_wq: ArrayLike) -> float:
        """Metric height of the camera above the anchored ground for this frame."""
        if self.z_ground is None or self.camera_height_m is None:
            raise RuntimeError("GroundAnchor.initialize must be called before use")
        if self.config.height_source == "calibrated":
            return self.camera_height_m
        return float(np.asarray(T_wq, float)[2, 3]) - self.z_ground

    def expected_height_b(self, T_wq: ArrayLike, scale_hint: float) -> float | None:
        """Ground height in backbone units implied by a scale guess (metres per unit), or None.

        E.g. with ``MotionResult.scale_from_rays`` as the hint, pass the result to
        :func:`ground_peak` as ``prior_height_b`` so a table top is not taken for the floor.
        """
        if not (np.isfinite(scale_hint) and scale_hint > 0):
            return None
        height = self.camera_height(T_wq)
        return -height / scale_hint if height > 0 else None

    def scale_for(
        self, T_wq: ArrayLike, ground: GroundEstimate, fallback_scale: float | None = None
    ) -> ScaleEstimate:
        """Metres per backbone unit for one frame.

        Uses the ground peak when found and the camera is above the anchored ground;
        otherwise ``fallback_scale`` (e.g. ``MotionResult.scale_from_rays``) when it is finite
        and positive; otherwise ``ScaleEstimate(nan, "none")``.
        """
        if not self.config.enabled:
            return ScaleEstimate(1.0, "disabled")
        height = self.camera_height(T_wq)
        if ground.found and ground.height_b < 0 and height > 0:
            return ScaleEstimate(height / -ground.height_b, "ground")
        if fallback_scale is not None and np.isfinite(fallback_scale) and fallback_scale > 0:
            return ScaleEstimate(float(fallback_scale), "fallback")
        return ScaleEstimate(float("nan"), "none")
