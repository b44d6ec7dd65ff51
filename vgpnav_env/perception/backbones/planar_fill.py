"""Piecewise-planar completion of a sweep depth map (textureless walls and floors of interiors).

The query image (at sweep resolution) is over-segmented by colour (Felzenszwalb's graph method);
per segment a plane is fitted to the confident inverse depths. A 3D plane ``n . X = c`` seen by a
pinhole camera has an inverse depth affine in the pixel coordinates, ``1/z = a u + b v + e``.
Per segment the best of ``hypotheses`` planes through 3 random confident pixels (most pixels
within ``inlier_tolerance``, relative) gives the inliers (the sweep's confident pixels on a
textureless wall are often mostly mismatches); a least-squares fit to them (all segments at once
from per-segment sums) is re-trimmed to the pixels within the tolerance three times. A segment is
filled when its plane is well supported: at least ``min_support`` inliers covering
``min_support_fraction`` of the segment, ``min_inlier_ratio`` of its confident pixels on the
plane, the inliers spread over ``min_spread`` of the segment's extent in u and v (no
extrapolation of a slope seen on one edge) and the filled inverse depths inside the swept range.
Its unconfident visible pixels then get the plane's depth, unless the confident pixels near them
contradict the plane (in a window of ``local_window`` x the image width, fewer than
``min_inlier_ratio`` of the confident pixels of accepted segments lie on their plane: an object
the segmentation merged into the floor's segment keeps its own few points instead of the floor's
depth), and a confidence above the pipeline's threshold (``OccupancyConfig.min_confidence``),
``fill_confidence`` x (0.8 + 0.2 x the inlier ratio's margin above ``min_inlier_ratio``). With
``snap_inliers`` the confident pixels on such a plane (its inliers) take the plane's depth too (the
fit averages their matching noise away); confident pixels off the plane keep their own depth, and
every confidence is kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from skimage.segmentation import felzenszwalb


@dataclass(frozen=True)
class PlanarFillConfig:
    """Segmentation (``segment_scale``, ``segment_sigma``, ``min_segment_size`` pixels at sweep
    scale), the support threshold ``support_confidence``, the plane acceptance tests,
    ``snap_inliers`` and the local test's window ``local_window`` (a fraction of the image width,
    0 = off; see the module docstring)."""

    segment_scale: float = 200.0
    segment_sigma: float = 0.5
    min_segment_size: int = 30
    support_confidence: float = 0.3
    hypotheses: int = 32
    inlier_tolerance: float = 0.08
    min_support: int = 30
    min_support_fraction: float = 0.04
    min_inlier_ratio: float = 0.5
    min_spread: float = 0.2
    fill_confidence: float = 0.4
    snap_inliers: bool = True
    local_window: float = 0.0

    def __post_init__(self) -> None:
        if self.hypotheses < 1:
            raise ValueError(f"hypotheses must be >= 1, got {self.hypotheses}")
        if self.min_support < 3:
            raise ValueError(f"min_support must be >= 3 (a plane has 3 parameters), got {self.min_support}")
        if not 0.0 < self.fill_confidence <= 1.0 or not 0.0 < self.support_confidence <= 1.0:
            raise ValueError("fill_confidence and support_confidence must be in (0, 1]")
        if not 0.0 <= self.local_window < 1.0:
            raise ValueError(
                f"local_window must be in [0, 1) (a fraction of the image width), got {self.local_window}"
            )
        if self.inlier_tolerance <= 0:
            raise ValueError(f"inlier_tolerance must be positive, got {self.inlier_tolerance}")


def fit_segment_planes(
    labels: NDArray[np.integer], inv_depth: NDArray[np.floating], support: NDArray[np.bool_]
) -> NDArray[np.float64]:
    """Least-squares plane ``1/z = a u + b v + e`` (rows of (a, b, e)) per label from the
    ``support`` pixels (NaN rows where fewer than 3 pixels or a degenerate layout)."""
    n = int(labels.max()) + 1
    v, u = np.indices(labels.shape, dtype=np.float64)
    lab, u, v, y = labels[support], u[support], v[support], inv_depth[support].astype(np.float64)
    feats = (u, v, np.ones_like(u))
    A = np.empty((n, 3, 3))
    b = np.empty((n, 3))
    for i, fi in enumerate(feats):
        b[:, i] = np.bincount(lab, fi * y, n)
        for j in range(i, 3):
            A[:, i, j] = A[:, j, i] = np.bincount(lab, fi * feats[j], n)
    ok = (A[:, 2, 2] >= 3) & (np.abs(np.linalg.det(A)) > 1e-6 * np.maximum(A[:, 2, 2], 1.0) ** 3)
    planes = np.full((n, 3), np.nan)
    planes[ok] = np.linalg.solve(A[ok], b[ok][..., None])[..., 0]
    return planes


def planar_fill(
    image: NDArray[np.uint8],
    inv_depth: NDArray[np.floating],
    confidence: NDArray[np.float32],
    visible: NDArray[np.bool_],
    inv_range: tuple[float, float],
    config: PlanarFillConfig,
) -> tuple[NDArray[np.float64], NDArray[np.float32]]:
    """Inverse depth and confidence (both (h, w), the sweep's) with the unconfident visible pixels of
    well-fitted planar segments of ``image`` (h, w, 3 RGB at sweep resolution) filled; ``inv_range``
    (low, high) bounds the accepted inverse depths. Confident pixels keep their confidence, and their
    inverse depth unless ``config.snap_inliers`` snaps them onto their segment's accepted plane."""
    cfg = config
    labels = felzenszwalb(
        image, scale=cfg.segment_scale, sigma=cfg.segment_sigma, min_size=cfg.min_segment_size
    )
    n = int(labels.max()) + 1
    v, u = np.indices(labels.shape, dtype=np.float64)
    confident = (confidence >= cfg.support_confidence) & visible
    support = ransac_support(labels, inv_depth, confident, cfg)
    for _ in range(3):
        planes = fit_segment_planes(labels, inv_depth, support)
        fitted = planes[labels, 0] * u + planes[labels, 1] * v + planes[labels, 2]
        with np.errstate(invalid="ignore"):
            on_plane = np.abs(fitted - inv_depth) <= cfg.inlier_tolerance * np.abs(inv_depth)
        support = confident & on_plane

    count = np.bincount(labels.ravel(), minlength=n)
    n_conf = np.bincount(labels[confident], minlength=n)
    n_in = np.bincount(labels[support], minlength=n)

    def spread(values: NDArray[np.float64], mask: NDArray[np.bool_] | None) -> NDArray[np.float64]:
        lab, x = (labels, values) if mask is None else (labels[mask], values[mask])
        total = np.maximum(np.bincount(lab.ravel(), minlength=n), 1)
        mean = np.bincount(lab.ravel(), x.ravel(), n) / total
        return np.sqrt(np.maximum(np.bincount(lab.ravel(), x.ravel() ** 2, n) / total - mean**2, 0.0))

    with np.errstate(invalid="ignore", divide="ignore"):
        inlier_ratio = n_in / np.maximum(n_conf, 1)
        spread_ok = (spread(u, support) >= cfg.min_spread * spread(u, None)) & (
            spread(v, support) >= cfg.min_spread * spread(v, None)
        )
    good = (
        np.isfinite(planes).all(axis=1)
        & (n_in >= cfg.min_support)
        & (n_in >= cfg.min_support_fraction * count)
        & (inlier_ratio >= cfg.min_inlier_ratio)
        & spread_ok
    )
    lo, hi = min(inv_range), max(inv_range)
    planar = good[labels]
    fill = planar & ~confident & visible & (fitted >= lo) & (fitted <= hi)
    if cfg.local_window > 0:
        fill &= ~_contradicted(
            planar & confident & ~support, planar & support, cfg.local_window, cfg.min_inlier_ratio
        )
    margin = np.clip((inlier_ratio - cfg.min_inlier_ratio) / max(1.0 - cfg.min_inlier_ratio, 1e-6), 0.0, 1.0)
    fill_conf = cfg.fill_confidence * (0.8 + 0.2 * margin)
    snapped = support & planar if cfg.snap_inliers else False
    out_inv = np.where(fill | snapped, fitted, inv_depth)
    out_conf = np.where(fill, np.maximum(confidence, fill_conf[labels]), confidence).astype(np.float32)
    return out_inv, out_conf


def _contradicted(
    off_plane: NDArray[np.bool_], on_plane: NDArray[np.bool_], window: float, min_ratio: float
) -> NDArray[np.bool_]:
    """Pixels whose window (``window`` x the image width, odd) holds too many confident pixels off
    their segment's accepted plane (``on_plane`` fewer than ``min_ratio`` of both): e.g. an object
    in front of the floor that the colour segmentation merged into the floor's segment."""
    size = max(3, int(round(window * off_plane.shape[1])) | 1)
    off = cv2.boxFilter(off_plane.astype(np.float32), -1, (size, size), normalize=False)
    on = cv2.boxFilter(on_plane.astype(np.float32), -1, (size, size), normalize=False)
    return on < min_ratio * (on + off)


def ransac_support(
    labels: NDArray[np.integer],
    inv_depth: NDArray[np.floating],
    confident: NDArray[np.bool_],
    cfg: PlanarFillConfig,
) -> NDArray[np.bool_]:
    """Per segment the confident pixels on the best of ``cfg.hypotheses`` planes through 3 random
    confident pixels of the segment (most pixels within ``inlier_tolerance``); seeded, vectorised."""
    rng = np.random.default_rng(0)
    rows, cols = np.nonzero(confident)
    lab = labels[rows, cols]
    order = np.argsort(lab, kind="stable")
    rows, cols, lab = rows[order], cols[order], lab[order]
    y = inv_depth[rows, cols].astype(np.float64)
    n = int(labels.max()) + 1
    count = np.bincount(lab, minlength=n)
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    segs = np.nonzero(count >= 3)[0]
    picks = start[segs, None, None] + (
        rng.random((len(segs), cfg.hypotheses, 3)) * count[segs, None, None]
    ).astype(int)
    A = np.stack([cols[picks], rows[picks], np.ones(picks.shape)], axis=-1).astype(np.float64)
    det = np.linalg.det(A)
    ok = np.abs(det) > 1e-6
    A[~ok] = np.eye(3)
    planes = np.linalg.solve(A, y[picks][..., None])[..., 0]
    planes[~ok] = np.nan
    seg_index = np.full(n, -1)
    seg_index[segs] = np.arange(len(segs))
    keep = seg_index[lab] >= 0
    p = planes[seg_index[lab[keep]]]
    pred = p[..., 0] * cols[keep, None] + p[..., 1] * rows[keep, None] + p[..., 2]
    with np.errstate(invalid="ignore"):
        inlier = np.abs(pred - y[keep, None]) <= cfg.inlier_tolerance * np.abs(y[keep, None])
    kept_count = count[segs]
    scores = np.add.reduceat(inlier.astype(np.int32), np.cumsum(kept_count) - kept_count, axis=0)
    best = np.full(n, 0)
    best[segs] = scores.argmax(axis=1)
    chosen = inlier[np.arange(keep.sum()), best[lab[keep]]]
    support = np.zeros_like(confident)
    support[rows[keep][chosen], cols[keep][chosen]] = True
    return support
