"""PRIVILEGED simulated backbone: ground-truth poses and depth, corrupted and rescaled.

It reads the renderer's true poses and depth (``Privileged``), so it is NOT a perception
method: it exists to train RL at speed and to isolate the downstream modules (motion
averaging, scale recovery, occupancy) from backbone errors. Output follows the backbone
contract: ``T_qi = inv(T_wq) @ T_wi`` with configurable noise, then translations and depths
multiplied by one random unknown scale (scale convention ``"random"``: log-uniform in
``scale_range``).

Noise model (all angles in degrees in the config, radians inside):

- rotation: each ``R_qi`` is perturbed by a rotation about a uniformly random axis whose
  angle is ``|N(0, rotation_noise_deg^2)|`` (so the RMS rotation error is the setting);
- translation direction: ``t_qi`` is turned about a random axis perpendicular to it by an
  angle ``|N(0, direction_noise_deg^2)|`` (length kept);
- depth: every pixel is multiplied by ``exp(N(0, depth_noise^2))`` (relative noise);
- outliers: each reference independently with probability ``outlier_fraction`` gets a
  uniformly random rotation and translation direction (length kept) and a confidence
  drawn uniformly from ``outlier_confidence``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from vgpnav_env.geometry import invert_pose
from vgpnav_env.perception.backbones.base import Backbone, BackboneOutput, Views


@dataclass(frozen=True)
class SimulatedConfig:
    rotation_noise_deg: float = 0.0
    direction_noise_deg: float = 0.0
    depth_noise: float = 0.0
    outlier_fraction: float = 0.0
    outlier_confidence: tuple[float, float] = (0.0, 1.0)
    inlier_confidence: float = 1.0
    scale_range: tuple[float, float] = (0.2, 5.0)
    n_matches: int = 500

    def __post_init__(self) -> None:
        if min(self.rotation_noise_deg, self.direction_noise_deg, self.depth_noise) < 0:
            raise ValueError("noise levels must be >= 0")
        if not 0.0 <= self.outlier_fraction <= 1.0:
            raise ValueError(f"outlier_fraction must be in [0, 1], got {self.outlier_fraction}")
        lo, hi = self.outlier_confidence
        if not 0.0 <= lo <= hi <= 1.0 or not 0.0 <= self.inlier_confidence <= 1.0:
            raise ValueError("confidences must lie in [0, 1] with outlier_confidence = (low, high)")
        if not 0.0 < self.scale_range[0] <= self.scale_range[1]:
            raise ValueError(f"scale_range must be 0 < low <= high, got {self.scale_range}")


def random_unit_vectors(rng: np.random.Generator, n: int) -> NDArray[np.float64]:
    v = rng.standard_normal((n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def perpendicular_unit_vectors(
    rng: np.random.Generator, directions: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Uniformly random unit vectors perpendicular to each row of ``directions`` (n, 3)."""
    d = directions / np.maximum(np.linalg.norm(directions, axis=1, keepdims=True), 1e-12)
    v = random_unit_vectors(rng, len(d))
    v -= np.einsum("ij,ij->i", v, d)[:, None] * d
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)


class SimulatedBackbone(Backbone):
    """PRIVILEGED: perturbed ground truth at a random unknown scale (see the module docstring)."""

    name = "simulated"
    privileged = True

    def __init__(
        self, config: SimulatedConfig | None = None, seed: int | np.random.Generator | None = None
    ) -> None:
        self.config = config or SimulatedConfig()
        self.rng = np.random.default_rng(seed)
        #: The scale drawn for the latest call (privileged, for evaluation and tests only).
        self.last_scale: float | None = None

    def reseed(self, rng: np.random.Generator) -> None:
        """A new noise stream seeded by one draw from ``rng`` (see :meth:`Backbone.reseed`)."""
        self.rng = np.random.default_rng(int(rng.integers(2**63)))

    def reconstruct(self, views: Views) -> BackboneOutput:
        references, camera, privileged = views.references, views.camera, views.privileged
        if privileged is None:
            raise ValueError(
                "the simulated backbone is privileged: pass `privileged=Privileged(T_wq, T_wi, query_depth)` "
                "with ground truth (or use the 'classical' backbone, which needs pixels only)"
            )
        cfg, rng = self.config, self.rng
        k = len(references)
        T_wi = np.asarray(privileged.T_wi, float).reshape(-1, 4, 4)
        if len(T_wi) != k:
            raise ValueError(f"privileged.T_wi has {len(T_wi)} poses for {k} references")
        gt_depth = np.asarray(privileged.query_depth, np.float32)
        if gt_depth.shape != (camera.height, camera.width):
            raise ValueError(
                f"privileged.query_depth shape {gt_depth.shape} != {(camera.height, camera.width)}"
            )

        T_qi = invert_pose(np.asarray(privileged.T_wq, float)) @ T_wi
        R = T_qi[:, :3, :3]
        t = T_qi[:, :3, 3]
        if cfg.rotation_noise_deg > 0:
            angles = np.abs(rng.normal(0.0, np.deg2rad(cfg.rotation_noise_deg), k))
            R = Rotation.from_rotvec(random_unit_vectors(rng, k) * angles[:, None]).as_matrix() @ R
        if cfg.direction_noise_deg > 0:
            angles = np.abs(rng.normal(0.0, np.deg2rad(cfg.direction_noise_deg), k))
            axes = perpendicular_unit_vectors(rng, t)
            t = np.einsum("kij,kj->ki", Rotation.from_rotvec(axes * angles[:, None]).as_matrix(), t)
        confidence = np.full(k, cfg.inlier_confidence)
        outlier = rng.random(k) < cfg.outlier_fraction
        n_out = int(outlier.sum())
        if n_out:
            R[outlier] = Rotation.random(n_out, random_state=rng).as_matrix()
            t[outlier] = random_unit_vectors(rng, n_out) * np.linalg.norm(t[outlier], axis=1, keepdims=True)
            confidence[outlier] = rng.uniform(*cfg.outlier_confidence, n_out)

        lo, hi = np.log(cfg.scale_range)
        scale = float(np.exp(rng.uniform(lo, hi)))
        self.last_scale = scale
        T_qi = np.tile(np.eye(4), (k, 1, 1))
        T_qi[:, :3, :3] = R
        T_qi[:, :3, 3] = t * scale

        valid = np.isfinite(gt_depth) & (gt_depth > 0)
        depth = self._noisy_depth(gt_depth, valid) * scale
        ref_depths = None
        if privileged.reference_depths is not None:
            gt_refs = np.asarray(privileged.reference_depths, np.float32)
            if gt_refs.shape != (k, *gt_depth.shape):
                raise ValueError(
                    f"privileged.reference_depths shape {gt_refs.shape} != {(k, *gt_depth.shape)}"
                )
            ref_valid = np.isfinite(gt_refs) & (gt_refs > 0)
            ref_depths = self._noisy_depth(gt_refs, ref_valid) * scale
        return BackboneOutput(
            T_qi=T_qi,
            confidence=confidence,
            n_matches=np.full(k, cfg.n_matches, np.int64),
            query_depth=depth.astype(np.float32),
            query_depth_confidence=valid.astype(np.float32),
            name=self.name,
            scale="random",
            reference_depths=None if ref_depths is None else ref_depths.astype(np.float32),
            scale_valid=np.ones(k, bool),
        )

    def _noisy_depth(self, depth: NDArray[np.float32], valid: NDArray[np.bool_]) -> NDArray[np.float32]:
        out = np.where(valid, depth, 0.0).astype(np.float32)
        if self.config.depth_noise > 0:
            out *= np.exp(self.rng.normal(0.0, self.config.depth_noise, out.shape)).astype(np.float32)
        return out
