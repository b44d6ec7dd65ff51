"""Accuracy and speed of the classical backbone on rendered views of a built-in scene.

Per trial: a query camera at the robot's camera height and pitch (1.2 m, 20 deg) at a random free
spot, and ``k`` references at 1.5 m, 0.3-2 m away, looking at the point the query sees at its image
centre (as a retrieval would return overlapping views). Reports, over all trials, the median
rotation and translation-direction errors of the confident pairs, the fraction of pairs that passed,
the query depth error on confident pixels (at the scale implied by the recovered baselines, and at
the best-fit scale), and the time per call with reference features cold and cached.

    python benchmarks/backbone_classical.py --scene home --trials 10 --k 10
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from numpy.typing import NDArray

from vgpnav_env.geometry import PinholeCamera, camera_pose, invert_pose, rotation_angle
from vgpnav_env.perception.backbones import ClassicalBackbone, ClassicalConfig
from vgpnav_env.render import MujocoRenderer
from vgpnav_env.robot import CAMERA_HEIGHT, CAMERA_PITCH_DEG, FOVY_DEG
from vgpnav_env.scenes.scene import Scene

PITCH = np.deg2rad(CAMERA_PITCH_DEG)


def free_view(depth: NDArray[np.float32], min_depth: float = 0.5) -> bool:
    """A usable view: (almost) everything hit, nothing closer than ``min_depth``."""
    finite = np.isfinite(depth) & (depth > 0)
    return finite.mean() > 0.95 and float(depth[finite].min()) > min_depth


def sees(camera: PinholeCamera, T_wc: NDArray[np.float64], depth: NDArray[np.float32], point) -> bool:
    """Whether ``point`` (W) is inside the image and not occluded (rendered depth agrees within 5%)."""
    (u, v), z = camera.project_world(T_wc, point)
    if not (z > 0 and 0 <= u < camera.width - 0.5 and 0 <= v < camera.height - 0.5):
        return False
    return abs(float(depth[round(v), round(u)]) - z) < 0.05 * z


def sample_trial(
    renderer: MujocoRenderer,
    bounds: NDArray[np.float64],
    k: int,
    rng: np.random.Generator,
    attempts: int = 200,
):
    """Query pose, rgb, depth and ``k`` reference poses/rgbs (None if no free query is found)."""
    camera = renderer.camera
    lo, hi = bounds[0, :2] + 0.5, bounds[1, :2] - 0.5
    for _ in range(attempts):
        T_wq = camera_pose([*rng.uniform(lo, hi), CAMERA_HEIGHT], rng.uniform(-np.pi, np.pi), PITCH)
        query = renderer.render(T_wq)
        if not free_view(query.depth):
            continue
        centre = (camera.height // 2, camera.width // 2)
        target = T_wq[:3, :3] @ (camera.rays()[centre] * query.depth[centre]) + T_wq[:3, 3]
        poses, images = [], []
        for _ in range(attempts):
            r, a = rng.uniform(0.3, 2.0), rng.uniform(-np.pi, np.pi)
            xy = T_wq[:2, 3] + r * np.array([np.cos(a), np.sin(a)])
            to_target = target[:2] - xy
            if np.linalg.norm(to_target) < 0.8:
                continue
            yaw = np.arctan2(to_target[1], to_target[0]) + rng.normal(0.0, np.deg2rad(10.0))
            T_wi = camera_pose([*xy, 1.5], yaw, PITCH)
            frame = renderer.render(T_wi)
            if free_view(frame.depth) and sees(camera, T_wi, frame.depth, target):
                poses.append(T_wi)
                images.append(frame.rgb)
            if len(poses) == k:
                return T_wq, query.rgb, query.depth, np.stack(poses), images
    return None


def direction_error_deg(a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    cos = a @ b / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def measure(
    scene: Scene, trials: int, k: int, seed: int, camera: PinholeCamera, config: ClassicalConfig
) -> dict:
    rng = np.random.default_rng(seed)
    renderer = MujocoRenderer(scene, camera)
    backbone = ClassicalBackbone(config)
    rot, direction, passed, pair_conf, pair_linked = [], [], [], [], []
    depth_baseline, depth_fit, confident_fraction = [], [], []
    t_cold, t_warm, stages = [], [], []
    for trial in range(trials):
        sample = sample_trial(renderer, scene.bounds, k, rng)
        if sample is None:
            raise RuntimeError(f"no free query view found in scene {scene.key}")
        T_wq, query, depth_gt, T_wi, refs = sample
        keys = [(trial, i) for i in range(k)]
        t0 = time.perf_counter()
        backbone(query, refs, camera, reference_keys=keys)
        t_cold.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        out = backbone(query, refs, camera, reference_keys=keys)
        t_warm.append(time.perf_counter() - t0)
        stages.append(out.timings)
        T_qi = invert_pose(T_wq) @ T_wi
        ok = out.confidence > 0
        passed.append(ok.mean())
        for i in np.flatnonzero(ok):
            rot.append(np.degrees(rotation_angle(out.T_qi[i, :3, :3], T_qi[i, :3, :3])))
            direction.append(direction_error_deg(out.T_qi[i, :3, 3], T_qi[i, :3, 3]))
            pair_conf.append(out.confidence[i])
            pair_linked.append(out.scale_valid[i])
        linked = out.scale_valid
        confident = (out.query_depth_confidence > 0.5) & np.isfinite(depth_gt)
        confident_fraction.append(confident.mean())
        if linked.any() and confident.any():
            ratios = np.linalg.norm(out.T_qi[linked, :3, 3], axis=1) / np.linalg.norm(
                T_qi[linked, :3, 3], axis=1
            )
            est, gt = out.query_depth[confident], depth_gt[confident]
            depth_baseline.append(np.median(np.abs(est / np.median(ratios) - gt) / gt))
            depth_fit.append(np.median(np.abs(est * np.median(gt / est) - gt) / gt))
    renderer.close()
    gross = (np.array(rot) > 5.0) | (np.array(direction) > 10.0)
    pair_conf, pair_linked = np.array(pair_conf), np.array(pair_linked, bool)
    return {
        "scene": scene.key,
        "trials": trials,
        "k": k,
        "pairs_passed": float(np.mean(passed)),
        "rotation_error_deg_median": float(np.median(rot)) if rot else None,
        "rotation_error_deg_p90": float(np.percentile(rot, 90)) if rot else None,
        "direction_error_deg_median": float(np.median(direction)) if direction else None,
        "direction_error_deg_p90": float(np.percentile(direction, 90)) if direction else None,
        "gross_pair_fraction": float(gross.mean()) if rot else None,
        "confidence_median_good_gross": [
            float(np.median(pair_conf[m])) if m.any() else None for m in (~gross, gross)
        ],
        "linked_fraction_good_gross": [
            float(pair_linked[m].mean()) if m.any() else None for m in (~gross, gross)
        ],
        "depth_rel_error_median_baseline_scale": float(np.median(depth_baseline)) if depth_baseline else None,
        "depth_rel_error_median_fit_scale": float(np.median(depth_fit)) if depth_fit else None,
        "depth_confident_fraction": float(np.mean(confident_fraction)),
        "time_cold_s_median": float(np.median(t_cold)),
        "time_cached_s_median": float(np.median(t_warm)),
        "stage_times_s_median": {key: float(np.median([s[key] for s in stages])) for key in stages[0]},
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--scene", default="home")
    parser.add_argument("--layout", default="base")
    parser.add_argument("--texture", default="realistic")
    parser.add_argument("--trials", type=int, default=10)
    parser.add_argument("--k", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    from vgpnav_env.scenes import load_scene

    scene = load_scene(args.scene, layout=args.layout, texture=args.texture)
    camera = PinholeCamera(320, 240, np.deg2rad(FOVY_DEG))
    print(json.dumps(measure(scene, args.trials, args.k, args.seed, camera, ClassicalConfig()), indent=2))


if __name__ == "__main__":
    main()
