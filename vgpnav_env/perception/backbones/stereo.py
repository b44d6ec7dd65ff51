"""Dense query depth from calibrated views: an NCC plane sweep (the classical backbone's MVS step).

Input: the query and reference images (uint8 RGB, one pinhole camera), each reference's pose
``T_iq`` (maps query-camera coordinates into reference ``i``; translations at the caller's
unknown scale) and sparse query depths at that scale (they bound the sweep). Output: a query
z-depth (H, W) float32 at the same scale (0 where unknown) and a confidence (H, W) in [0, 1].

The sweep runs over fronto-parallel inverse-depth planes at reduced resolution (the sparse-depth
range, plus coarser planes down to a fraction of the median sparse depth for near walls); each
reference is warped onto the query per plane and scored by windowed NCC (NaN where it does not
see the pixel); per pixel the mean of the ``keep_best`` best references counts (occlusions and a
few references with wrong poses are outvoted). Winner-take-all with a small window gives the
depth; a second winner with a larger window must agree, else the pixel is not confident (on the
home build this check let the small window reach the coverage of a 7x7 window at fewer confident
outliers: Comp -0.009 m at equal Acc). Confidence = matching score * uniqueness * texture *
visibility (0 where no reference sees the pixel; depth 0 there).

Piecewise-planar completion (:mod:`.planar_fill`, ``SweepConfig.planar``, on by default) then fills
unconfident pixels of well-fitted planar segments.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from vgpnav_env.geometry import PinholeCamera
from vgpnav_env.perception.backbones.planar_fill import PlanarFillConfig, planar_fill
from vgpnav_env.perception.backbones.threads import resolve_threads, thread_map


@dataclass(frozen=True)
class SweepConfig:
    """Knobs of the plane sweep: image ``scale``, number of ``planes``, per pixel the mean NCC of
    the ``keep_best`` best references, NCC window (px at sweep scale), depth range from
    sparse-depth percentiles widened by ``depth_range_margin``; confidence terms ``min_ncc``,
    ``full_confidence_margin`` (uniqueness), ``min_texture_std`` (grey levels). Window check
    (``check_window`` > 0): a second winner-take-all with that larger window must agree within
    ``window_agreement`` (inverse depth times the median sparse depth; the check scores every
    ``check_plane_stride``-th plane) or the confidence is 0;
    agreeing pixels get ``confidence_gain`` times the ``ncc_window`` confidence (clipped to 1).
    Near planes: from ``near_depth_factor`` times the median sparse depth (0 = off) to the depth
    range, ``near_plane_step`` times coarser in inverse depth.
    Optional speckle removal (``speckle_size`` > 0 pixels at sweep scale) and piecewise-planar
    completion of unconfident pixels (``planar``, None = off; see :mod:`.planar_fill`)."""

    scale: float = 0.5
    planes: int = 64
    keep_best: int = 2
    ncc_window: int = 5
    check_window: int = 11
    window_agreement: float = 0.08
    check_plane_stride: int = 2
    confidence_gain: float = 3.0
    depth_range_percentiles: tuple[float, float] = (2.0, 98.0)
    depth_range_margin: tuple[float, float] = (0.7, 1.5)
    near_depth_factor: float = 0.25
    near_plane_step: float = 3.0
    min_ncc: float = 0.4
    full_confidence_margin: float = 0.1
    min_texture_std: float = 0.5
    speckle_size: int = 0
    speckle_confidence: float = 0.3
    speckle_max_diff: float = 1.0
    planar: PlanarFillConfig | None = field(default_factory=PlanarFillConfig)

    def __post_init__(self) -> None:
        if not 0.0 < self.scale <= 1.0:
            raise ValueError(f"sweep scale must be in (0, 1], got {self.scale}")
        if self.planes < 3 or self.ncc_window < 3 or self.ncc_window % 2 == 0:
            raise ValueError("sweep planes must be >= 3 and ncc_window an odd number >= 3")
        if self.check_window and (self.check_window < 3 or self.check_window % 2 == 0):
            raise ValueError(f"check_window must be 0 (off) or an odd number >= 3, got {self.check_window}")
        if self.check_plane_stride < 1:
            raise ValueError(f"check_plane_stride must be >= 1, got {self.check_plane_stride}")
        if self.keep_best < 1:
            raise ValueError(f"keep_best must be >= 1, got {self.keep_best}")


def grayscale(image: NDArray[np.uint8]) -> NDArray[np.uint8]:
    return cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)


def best_mean(values: NDArray[np.float32], keep: int) -> NDArray[np.float32]:
    """Per pixel, the mean of the ``keep`` largest finite values along axis 0 (NaN if none).

    Occlusion-robust aggregation of per-reference NCC: a reference that sees an occluder at a
    pixel is dropped as long as ``keep`` others see it. See :func:`top_mean` (-inf marks unseen).
    """
    return top_mean(np.where(np.isfinite(values), values, -np.inf).astype(np.float32), keep)


def top_mean(values: NDArray[np.float32], keep: int) -> NDArray[np.float32]:
    """Per pixel, the mean of the ``keep`` largest values > -inf along axis 0 (NaN if none).

    The ``keep`` largest values so far are updated reference by reference with element-wise max /
    min into preallocated arrays (a few array operations for the handful of references; numpy's
    sort and partition along a short leading axis were slower).
    """
    keep = min(keep, len(values))
    shape = values.shape[1:]
    if keep < 1:
        return np.full(shape, np.nan, np.float32)
    tops = [values[0].copy(), *(np.full(shape, -np.inf, np.float32) for _ in range(keep - 1))]
    spare = [np.empty(shape, np.float32) for _ in range(min(keep - 1, 2))]
    for v in values[1:]:
        carry = v
        for j in range(keep - 1):
            low = spare[j % 2]  # never the array ``carry`` refers to
            np.minimum(tops[j], carry, out=low)
            np.maximum(tops[j], carry, out=tops[j])
            carry = low
        np.maximum(tops[-1], carry, out=tops[-1])
    total = np.zeros(shape, np.float32)
    count = np.zeros(shape, np.float32)
    for t in tops:
        seen = t > -np.inf
        total += np.where(seen, t, np.float32(0.0))
        count += seen
    with np.errstate(invalid="ignore", divide="ignore"):
        return total / count


def speckles(
    inv_depth: NDArray[np.floating], confident: NDArray[np.bool_], step: float, cfg: SweepConfig
) -> NDArray[np.bool_]:
    """Confident pixels in 4-connected patches of fewer than ``speckle_size`` pixels whose neighbours
    differ by at most ``speckle_max_diff`` plane steps (isolated mismatches, cv2.filterSpeckles)."""
    levels = np.round((inv_depth - inv_depth[confident].min()) / step * 4.0) + 1.0 if confident.any() else 0
    disparity = np.where(confident, levels, 0).astype(np.int16)
    cv2.filterSpeckles(disparity, 0, cfg.speckle_size, round(cfg.speckle_max_diff * 4))
    return confident & (disparity == 0)


def plane_sweep(
    query: NDArray[np.uint8],
    references: list[NDArray[np.uint8]],
    T_iq: NDArray[np.float64],
    camera: PinholeCamera,
    sparse_depths: NDArray[np.float64],
    config: SweepConfig | None = None,
    threads: int = 1,
    timings: dict[str, float] | None = None,
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Query depth (H, W) and confidence from an NCC sweep of fronto-parallel inverse-depth planes.

    A plane ``z = d`` in the query frame induces ``x_i ~ K (R + t n^T / d) K^-1 x_q``; each
    reference is warped onto the query per plane, scored by windowed NCC (unseen where the
    reference does not see the pixel) and averaged over the best references that do. The planes
    are scored in chunks on ``threads`` threads (<= 0: all cores; the result does not depend on it).
    ``timings``: the piecewise-planar completion's wall and process CPU seconds are added to its
    ``completion`` and ``completion_cpu`` (the rest of the call is the sweep proper).
    """
    cfg = config or SweepConfig()
    w = max(8, round(camera.width * cfg.scale))
    h = max(8, round(camera.height * cfg.scale))
    small = camera.resized(w, h)
    K, K_inv = small.K, np.linalg.inv(small.K)
    windows = [cfg.ncc_window] + ([cfg.check_window] if cfg.check_window else [])

    def prepare(image: NDArray[np.uint8]) -> NDArray[np.float32]:
        return cv2.resize(grayscale(image), (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)

    q = prepare(query)
    refs = [prepare(r) for r in references]
    inv_depths = sweep_planes(sparse_depths, cfg)
    n = np.array([0.0, 0.0, 1.0])
    # (planes, refs, 3, 3) homographies mapping query pixels into each reference.
    R, t = T_iq[:, :3, :3], T_iq[:, :3, 3]
    homographies = K @ (R[None] + (t[:, :, None] * n)[None] * inv_depths[:, None, None, None]) @ K_inv
    stack = _RefStack(q, len(refs), windows)
    scores = np.empty((len(windows), len(inv_depths), h, w), np.float32)

    def score(chunk: range) -> None:
        buffers = stack.buffers()
        for p in chunk:
            windows_now = [k for k in range(len(windows)) if k == 0 or p % cfg.check_plane_stride == 0]
            stack.score(refs, homographies[p], windows_now, min(cfg.keep_best, len(refs)), buffers, scores, p)

    n_chunks = 1 if resolve_threads(threads) <= 1 else 4 * resolve_threads(threads)
    thread_map(score, _chunks(len(inv_depths), n_chunks), threads)
    query_var = [var for _, var in stack.query_stats]
    inv_depth, conf_small, visible = winner_take_all(scores[0], inv_depths, query_var[0], cfg)
    if cfg.check_window:
        stride = cfg.check_plane_stride
        inv_check, _, _ = winner_take_all(scores[1][::stride], inv_depths[::stride], query_var[1], cfg)
        agree = np.abs(inv_depth - inv_check) * np.median(sparse_depths) <= cfg.window_agreement
        conf_small = np.where(agree, np.minimum(conf_small * cfg.confidence_gain, 1.0), 0.0).astype(
            np.float32
        )
    if cfg.speckle_size > 0:
        step = abs(inv_depths[1] - inv_depths[0])
        conf_small[speckles(inv_depth, conf_small >= cfg.speckle_confidence, step, cfg)] = 0.0
    if cfg.planar is not None:
        t0, c0 = time.perf_counter(), time.process_time()
        colour = cv2.resize(np.ascontiguousarray(query), (w, h), interpolation=cv2.INTER_AREA)
        inv_range = (float(inv_depths.min()), float(inv_depths.max()))
        inv_depth, conf_small = planar_fill(colour, inv_depth, conf_small, visible, inv_range, cfg.planar)
        if timings is not None:
            timings["completion"] = timings.get("completion", 0.0) + time.perf_counter() - t0
            timings["completion_cpu"] = timings.get("completion_cpu", 0.0) + time.process_time() - c0
    depth_small = np.where(visible, 1.0 / inv_depth, 0.0).astype(np.float32)
    depth = cv2.resize(depth_small, (camera.width, camera.height), interpolation=cv2.INTER_NEAREST)
    conf = cv2.resize(conf_small, (camera.width, camera.height), interpolation=cv2.INTER_LINEAR)
    return depth, np.clip(conf, 0.0, 1.0)


def sweep_planes(sparse_depths: NDArray[np.float64], cfg: SweepConfig) -> NDArray[np.float64]:
    """The swept inverse depths, near to far: ``cfg.planes`` over the widened sparse-depth range,
    preceded by coarser planes down to ``near_depth_factor`` x the median sparse depth."""
    lo, hi = np.percentile(sparse_depths, cfg.depth_range_percentiles)
    d_min, d_max = lo * cfg.depth_range_margin[0], hi * cfg.depth_range_margin[1]
    inv_depths = np.linspace(1.0 / d_min, 1.0 / d_max, cfg.planes)
    near = cfg.near_depth_factor * float(np.median(sparse_depths))
    if 0 < near < d_min:
        # Surfaces nearer than the sparse points (a wall beside the robot) get coarser planes: the
        # depth error of one inverse-depth step shrinks with the square of the depth.
        coarse = cfg.near_plane_step * (inv_depths[0] - inv_depths[1])
        inv_depths = np.concatenate(
            [np.arange(1.0 / near, inv_depths[0] + 0.5 * coarse, -coarse)[:-1], inv_depths]
        )
    return inv_depths


def _chunks(n: int, parts: int) -> list[range]:
    """``range(n)`` split into at most ``parts`` contiguous, nearly equal ranges."""
    bounds = np.linspace(0, n, min(parts, n) + 1).round().astype(int)
    return [range(a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=True) if b > a]


class _RefStack:
    """Windowed NCC of warped references against the query, all references in one tall image.

    Each reference occupies ``h`` rows padded by ``g`` mirrored rows above and below (OpenCV's
    default border, BORDER_REFLECT_101), so that one box filter serves every reference and no
    window reaches into the next one: the NCC equals the per-image one.
    """

    def __init__(self, q: NDArray[np.float32], n_refs: int, windows: list[int]) -> None:
        self.h, self.w = q.shape
        self.n_refs, self.windows = n_refs, windows
        self.g = max(windows) // 2
        self.rows = self.h + 2 * self.g
        self.stacked_q = self.stack([q] * n_refs)
        self.query_stats = []  # per window: stacked (mean, variance), single variance
        self.stacked_stats = []
        for size in windows:
            mu = cv2.boxFilter(q, -1, (size, size))
            var = np.maximum(cv2.boxFilter(q * q, -1, (size, size)) - mu * mu, 0.0)
            self.query_stats.append((mu, var))
            self.stacked_stats.append((self.stack([mu] * n_refs), self.stack([var] * n_refs)))
        self.kernels = [np.ones((size, size), np.uint8) for size in windows]
        self.minus_inf = np.full((n_refs * self.rows, self.w), -np.inf, np.float32)

    def stack(self, images: list[NDArray[np.float32]]) -> NDArray[np.float32]:
        g = self.g
        return np.concatenate([cv2.copyMakeBorder(i, g, g, 0, 0, cv2.BORDER_REFLECT_101) for i in images])

    def buffers(self) -> dict[str, NDArray[np.float32]]:
        """Work arrays of one thread."""
        shape = (self.n_refs * self.rows, self.w)
        return {
            name: np.empty(shape, np.float32) for name in ("warped", "square", "cross", "a", "b", "c", "d")
        }

    def score(
        self,
        refs: list[NDArray[np.float32]],
        homographies: NDArray[np.float64],
        windows: list[int],
        keep: int,
        buf: dict[str, NDArray[np.float32]],
        scores: NDArray[np.float32],
        plane: int,
    ) -> None:
        """``scores[k, plane]`` = mean NCC of the ``keep`` best references for each window index k."""
        h, w, g, rows = self.h, self.w, self.g, self.rows
        warped = buf["warped"]
        for r, (ref, H) in enumerate(zip(refs, homographies, strict=True)):
            top = r * rows + g
            cv2.warpPerspective(
                ref,
                H,
                (w, h),
                dst=warped[top : top + h],
                flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=float("nan"),
            )
            warped[top - g : top] = warped[top + g : top : -1]
            warped[top + h : top + h + g] = warped[top + h - 2 : top + h - 2 - g : -1]
        # Box filters keep running sums along rows, so one NaN would blank the rest of its row (a
        # reference leaving the view on the left hid the whole image): zero the unseen pixels and
        # mark windows that reach them instead.
        # OpenCV's masked copies: numpy's masked assignment cost ~8 multiplications.
        unseen = np.isnan(warped).view(np.uint8)
        cv2.patchNaNs(warped, 0.0)
        square, cross, a, b, c, d = (buf[name] for name in ("square", "cross", "a", "b", "c", "d"))
        np.multiply(warped, warped, out=square)
        np.multiply(self.stacked_q, warped, out=cross)
        for k in windows:
            size = self.windows[k]
            mu_q, var_q = self.stacked_stats[k]
            cv2.boxFilter(warped, -1, (size, size), dst=a)  # mean of the warped reference
            cv2.boxFilter(square, -1, (size, size), dst=b)
            cv2.boxFilter(cross, -1, (size, size), dst=c)
            # ncc = (E[qw] - mu_q mu_w) / sqrt(var_q * max(E[w^2] - mu_w^2, 0) + 1e-3)
            np.subtract(c, np.multiply(mu_q, a, out=d), out=c)
            np.multiply(a, a, out=a)
            np.subtract(b, a, out=b)
            np.maximum(b, 0.0, out=b)
            np.multiply(b, var_q, out=b)
            b += 1e-3
            np.sqrt(b, out=b)
            np.divide(c, b, out=c)
            hidden = cv2.dilate(unseen, self.kernels[k], borderValue=0)  # a window reaches an unseen pixel
            cv2.copyTo(self.minus_inf, hidden, c)
            per_ref = c.reshape(self.n_refs, rows, w)[:, g : g + h]
            scores[k, plane] = top_mean(per_ref, keep)


def winner_take_all(
    scores: NDArray[np.float32], inv_depths: NDArray[np.float64], var_q: NDArray[np.float32], cfg: SweepConfig
) -> tuple[NDArray[np.float64], NDArray[np.float32], NDArray[np.bool_]]:
    """Per pixel the best plane's inverse depth (parabolic sub-plane refinement), its confidence
    (score * uniqueness * texture * visibility) and whether any reference sees the pixel, from
    NCC ``scores`` (planes, h, w; NaN unseen) and the query's windowed variance ``var_q``."""
    n_planes, h, w = scores.shape
    unseen = np.isnan(scores)
    visible = ~unseen.all(axis=0)
    filled = scores.copy()
    np.copyto(filled, -1.0, where=unseen)
    best = filled.argmax(axis=0)
    rows, cols = np.indices((h, w))
    s0 = filled[best, rows, cols]
    prev = filled[np.maximum(best - 1, 0), rows, cols]
    nxt = filled[np.minimum(best + 1, n_planes - 1), rows, cols]
    curvature = prev + nxt - 2.0 * s0
    interior = (best > 0) & (best < n_planes - 1) & (curvature < -1e-6)
    offset = np.where(interior, 0.5 * (prev - nxt) / np.where(interior, curvature, 1.0), 0.0)
    inv_depth = np.interp(best + np.clip(offset, -0.5, 0.5), np.arange(n_planes), inv_depths)

    # Uniqueness: best score minus the best score outside a +-2 plane neighbourhood.
    for shift in range(-2, 3):
        filled[np.clip(best + shift, 0, n_planes - 1), rows, cols] = -1.0
    second = filled.max(axis=0)
    score_term = np.clip((s0 - cfg.min_ncc) / (1.0 - cfg.min_ncc), 0.0, 1.0)
    margin_term = np.clip((s0 - second) / cfg.full_confidence_margin, 0.0, 1.0)
    texture_term = np.clip(np.sqrt(var_q) / cfg.min_texture_std - 1.0, 0.0, 1.0)
    conf = (score_term * margin_term * texture_term * visible * interior).astype(np.float32)
    return inv_depth, conf, visible
