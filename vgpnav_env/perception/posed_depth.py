"""Dense query depth under a localized pose: the plane sweep re-run with the database's metric poses.

The classical backbone sweeps the query against its references at the relative poses of the
two-view pairs (:mod:`~vgpnav_env.perception.backbones.stereo`), before any pose is known: a pair
whose two-view pose is wrong but scale-linked still enters the sweep, and a frame with one or two
pairs has one or two sweep references. Once the pose ``T_wc`` is localized and verified, the
relative pose of EVERY database camera is known metrically (``T_iq = T_wi^-1 T_wc``), so the
depth is swept again:

- references: up to ``live_references`` of the sequence's recent mapped frames
  (:class:`RecentFrames`: they see the layout as it is now, where the database's images may still
  show furniture since moved), then the backbone's own sweep references (two-view pairs that
  passed), then the database cameras, up to ``references`` in all; the frames and cameras
  considered lie within ``radius`` metres and ``max_angle_deg``, at least ``min_baseline`` metres
  away (:func:`~vgpnav_env.perception.retrieval.nearby_cameras`), ranked by how much of the frame's
  first points (``points_w``) they see (the fraction that projects inside their image, minus
  ``distance_weight`` per metre of baseline);
- depth range: the first points' depths (metres);
- output: a METRIC query z-depth (H, W) and its confidence, no scale left to recover.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from vgpnav_env.geometry import PinholeCamera, invert_pose
from vgpnav_env.perception.backbones.planar_fill import PlanarFillConfig
from vgpnav_env.perception.backbones.stereo import SweepConfig, plane_sweep
from vgpnav_env.perception.retrieval import nearby_cameras


@dataclass(frozen=True)
class PosedDepthConfig:
    """The re-sweep after localization (module docstring); ``enabled`` False keeps the backbone's
    depth. ``sample_stride``: every that many of the first points score the overlap.
    ``recent_frames``: how many of the sequence's last mapped frames :class:`RecentFrames` keeps.
    ``sweep``: the plane sweep's settings (the map's depth; the backbone's own sweep, which serves
    the ground peak, has its own in :class:`~vgpnav_env.perception.backbones.classical.ClassicalConfig`).
    Only the map's planar completion checks its planes locally (``PlanarFillConfig.local_window``):
    an object the colour segmentation merges into the floor's segment is not painted as floor."""

    enabled: bool = True
    references: int = 5
    radius: float = 2.0
    max_angle_deg: float = 45.0
    min_baseline: float = 0.15
    distance_weight: float = 0.1
    sample_stride: int = 7
    live_references: int = 2
    recent_frames: int = 12
    sweep: SweepConfig = field(default_factory=lambda: SweepConfig(planar=PlanarFillConfig(local_window=0.1)))

    def __post_init__(self) -> None:
        if self.references < 1 or self.sample_stride < 1:
            raise ValueError(f"references and sample_stride must be >= 1, got {self}")
        if not 0 <= self.live_references < self.references or self.recent_frames < 0:
            raise ValueError(f"need 0 <= live_references < references and recent_frames >= 0, got {self}")
        if self.radius <= self.min_baseline or self.min_baseline < 0 or not 0 < self.max_angle_deg <= 180:
            raise ValueError(f"need 0 <= min_baseline < radius and max_angle_deg in (0, 180], got {self}")


def _by_overlap(
    T_w: NDArray[np.float64],
    T_wc: NDArray[np.float64],
    points_w: NDArray[np.float64],
    camera: PinholeCamera,
    config: PosedDepthConfig,
) -> NDArray[np.int64]:
    """Indices of the cameras ``T_w`` (M, 4, 4) near ``T_wc`` (:func:`nearby_cameras` with the
    config's radius, angle and baseline), best first by the fraction of every ``sample_stride``-th
    of ``points_w`` (N, 3, W) inside their image minus ``distance_weight`` x baseline."""
    cfg = config
    near = nearby_cameras(T_w, T_wc, cfg.radius, cfg.max_angle_deg, min_distance=cfg.min_baseline).index
    sample = np.asarray(points_w, float)[:: cfg.sample_stride]
    if len(near) == 0 or len(sample) == 0:
        return near[:0]
    T_iw = invert_pose(T_w[near])
    P = np.einsum("mij,nj->mni", T_iw[:, :3, :3], sample) + T_iw[:, None, :3, 3]
    uv, z = camera.project(P)
    inside = (z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] <= camera.width - 1)
    inside &= (uv[..., 1] >= 0) & (uv[..., 1] <= camera.height - 1)
    distance = np.linalg.norm(T_w[near, :3, 3] - T_wc[:3, 3], axis=1)
    score = inside.mean(axis=1) - cfg.distance_weight * distance
    return near[np.argsort(-score, kind="stable")]


def posed_references(
    T_wc: NDArray[np.float64],
    T_w: NDArray[np.float64],
    fixed: NDArray[np.int64],
    points_w: NDArray[np.float64],
    camera: PinholeCamera,
    config: PosedDepthConfig,
    count: int | None = None,
) -> NDArray[np.int64]:
    """Database indices to sweep a query at ``T_wc`` against: ``fixed`` first, then the cameras
    of ``T_w`` (M, 4, 4) near ``T_wc`` (:func:`_by_overlap`), ``count`` in all (default
    ``config.references``)."""
    count = config.references if count is None else count
    picked = [int(i) for i in fixed][:count]
    if len(picked) < count:
        ranked = [int(i) for i in _by_overlap(T_w, T_wc, points_w, camera, config) if i not in picked]
        picked += ranked[: count - len(picked)]
    return np.array(picked, np.int64)


class RecentFrames:
    """The last ``size`` frames (RGB, camera pose ``T_wc`` in W) a sequence mapped: references of
    the map's sweep that see the layout as it is now (module docstring)."""

    def __init__(self, size: int) -> None:
        self._frames: deque[tuple[NDArray[np.uint8], NDArray[np.float64]]] = deque(maxlen=size)

    def __len__(self) -> int:
        return len(self._frames)

    def add(self, rgb: NDArray[np.uint8], T_wc: NDArray[np.float64]) -> None:
        """Keep a copy of the frame (a caller may reuse its image buffer)."""
        if self._frames.maxlen:
            self._frames.append((np.array(rgb, np.uint8), np.array(T_wc, float)))

    def select(
        self,
        T_wc: NDArray[np.float64],
        points_w: NDArray[np.float64],
        camera: PinholeCamera,
        config: PosedDepthConfig,
    ) -> tuple[list[NDArray[np.uint8]], NDArray[np.float64]]:
        """Up to ``config.live_references`` frames to sweep a query at ``T_wc`` against
        (:func:`_by_overlap`): their images and poses (k, 4, 4)."""
        if not self._frames or config.live_references == 0:
            return [], np.zeros((0, 4, 4))
        T_w = np.stack([T for _, T in self._frames])
        best = _by_overlap(T_w, T_wc, points_w, camera, config)[: config.live_references]
        return [self._frames[i][0] for i in best], T_w[best]


def posed_depth(
    query: NDArray[np.uint8],
    references: list[NDArray[np.uint8]],
    T_wi: NDArray[np.float64],
    T_wc: NDArray[np.float64],
    camera: PinholeCamera,
    depths_m: NDArray[np.float64],
    sweep: SweepConfig | None = None,
    threads: int = 1,
    timings: dict[str, float] | None = None,
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Metric query z-depth (H, W; 0 where unknown) and confidence of the plane sweep of ``query``
    at ``T_wc`` against ``references`` at their poses ``T_wi`` (k, 4, 4), over the range of the
    depths ``depths_m`` (metres, e.g. the query's first points); ``timings`` as in
    :func:`~vgpnav_env.perception.backbones.stereo.plane_sweep`."""
    T_iq = invert_pose(np.asarray(T_wi, float)) @ np.asarray(T_wc, float)
    depths = np.asarray(depths_m, float)
    return plane_sweep(query, references, T_iq, camera, depths, sweep, threads=threads, timings=timings)
