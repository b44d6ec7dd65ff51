"""How much a known camera mount would sharpen stage 4's pose, per frame, on builds.

    python benchmarks/mount_constraint.py SCENE_OR_BUILD_DIR [...] [--height-errors 0.01 0.03]

The frames are :func:`metric_centre.stage_four_frames` (every query frame whose motion averaging
places more than one reference, with the references tracking chooses around its true pose). Each
frame's pose is stage 4's (:func:`~vgpnav_env.perception.resection.resect`, default settings); it
is then refined again over the same evidence (the triangulated points by reprojection and every
explained match by its Sampson distance to its reference, Cauchy loss) with fewer degrees of
freedom: the camera level (roll 0; x, y, z, yaw, pitch free), its pitch known as well (x, y, z,
yaw), its height and pitch known (x, y, yaw: a robot's planar pose), or the level camera with
the mount as a soft prior (height 2 cm, pitch 0.5 deg, one sigma). The localization builds'
query cameras change height (1.15-1.25 m) and pitch (15-30 deg) from frame to frame, so the known
height and pitch are each frame's TRUE ones, read from the truth: the numbers bound what a robot
with a calibrated mount could gain, and ``--height-errors`` shows what an error in the known height
(metres, added to the truth) costs. Columns: frames within 5 cm / 5 deg, median and p90 position
error, median rotation error, CPU per frame of the refinement.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np
from metric_centre import StageFourFrame, scene_build, stage_four_frames
from numpy.typing import NDArray
from scipy.optimize import least_squares

from vgpnav_env.eval.perception_runs import pose_errors
from vgpnav_env.geometry import camera_pose, camera_yaw_pitch
from vgpnav_env.perception.backbones.threads import configure_threads
from vgpnav_env.perception.resection import ResectionConfig, reference_points
from vgpnav_env.perception.verify.support import explained_matches, match_errors

#: Residuals are clipped here (in units of their pixel threshold) so that a point behind the
#: camera stays finite.
_CLIP = 50.0


def refine(
    T_wq: NDArray[np.float64],
    parametrize: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    start: NDArray[np.float64],
    f: StageFourFrame,
    config: ResectionConfig,
    prior: Callable[[NDArray[np.float64]], NDArray[np.float64]] | None = None,
) -> NDArray[np.float64]:
    """The pose ``parametrize(x)`` (T_wc) whose x, started at ``start``, best explains the frame
    ``f``'s points and matches that ``T_wq`` explains (Cauchy loss, residuals in units of the
    resection's reprojection and hybrid thresholds), plus the residuals ``prior(x)`` if given."""
    kept = explained_matches(T_wq, f.T_wi, f.out.matches, f.camera, config.epipolar_px)
    pixels, points = reference_points(f.T_wi, kept, f.camera, config.reprojection_px, config.min_angle_deg)

    def residuals(x: NDArray[np.float64]) -> NDArray[np.float64]:
        T = parametrize(x)
        reprojection = (f.camera.project_world(T, points)[0] - pixels).ravel() / config.reprojection_px
        sampson = [e[0] for e in match_errors(T[None], f.T_wi, kept, f.camera)]
        single = np.concatenate(sampson) / (config.hybrid_epipolar_px or 1.0) if sampson else np.zeros(0)
        r = np.concatenate([reprojection, single, prior(x) if prior is not None else []])
        return np.clip(np.nan_to_num(r, nan=_CLIP, posinf=_CLIP, neginf=-_CLIP), -_CLIP, _CLIP)

    x = least_squares(residuals, start, loss="cauchy", f_scale=1.0, diff_step=1e-6).x
    return parametrize(x)


def variants(T: NDArray[np.float64], z: float, pitch: float, height_errors: list[float]) -> dict:
    """name -> (parametrization, start, prior) of each constrained refinement of the pose ``T``,
    given the frame's true camera height ``z`` and pitch (radians)."""
    yaw0, pitch0 = camera_yaw_pitch(T)
    x, y, z0 = T[:3, 3]
    level = np.array([x, y, z0, yaw0, pitch0])
    out = {
        "level (roll 0)": (lambda p: camera_pose(p[:3], p[3], p[4]), level, None),
        "level, pitch known": (lambda p: camera_pose(p[:3], p[3], pitch), np.array([x, y, z0, yaw0]), None),
    }
    for dz in [0.0, *height_errors]:
        name = "height and pitch known" + (f", height {dz * 100:+g} cm" if dz else "")
        out[name] = (
            lambda p, h=z + dz: camera_pose([p[0], p[1], h], p[2], pitch),
            np.array([x, y, yaw0]),
            None,
        )
    for dz in height_errors:
        # The mount as a soft prior: height within 2 cm, pitch within 0.5 deg (one sigma each).
        out[f"level, mount prior (2 cm, 0.5 deg), height {dz * 100:+g} cm"] = (
            lambda p: camera_pose(p[:3], p[3], p[4]),
            level,
            lambda p, h=z + dz: np.array([(p[2] - h) / 0.02, (p[4] - pitch) / np.radians(0.5)]),
        )
    return out


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("scenes", nargs="+")
    parser.add_argument("--stride", type=int, default=1, help="every this many query frames")
    parser.add_argument("--height-errors", type=float, nargs="*", default=[0.01, 0.03])
    args = parser.parse_args()
    configure_threads(1)
    config = ResectionConfig()
    header = ["scene", "frames", "pose", "within 5 cm / 5 deg", "median (m)", "p90 (m)", "rotation (deg)"]
    print("| " + " | ".join([*header, "CPU ms / frame"]) + " |")
    print("|---" * (len(header) + 1) + "|")
    for scene in args.scenes:
        errors: dict[str, list[tuple[float, float]]] = {}
        cpu: dict[str, float] = {}
        for f in stage_four_frames(scene_build(scene), args.stride):
            T = f.resected(f.centre(), config)
            poses = {"stage 4 (6 DoF, default)": T}
            z, pitch = float(f.T_true[2, 3]), camera_yaw_pitch(f.T_true)[1]
            for name, (parametrize, start, prior) in variants(T, z, pitch, args.height_errors).items():
                t0 = time.process_time()
                poses[name] = refine(T, parametrize, start, f, config, prior)
                cpu[name] = cpu.get(name, 0.0) + time.process_time() - t0
            for name, P in poses.items():
                errors.setdefault(name, []).append(pose_errors(P, f.T_true))
        for name, rows in errors.items():
            e = np.array(rows)
            right = int(((e[:, 0] < 0.05) & (e[:, 1] < 5.0)).sum())
            print(
                f"| {scene} | {len(e)} | {name} | {right} | {np.median(e[:, 0]):.4f} | "
                f"{np.percentile(e[:, 0], 90):.3f} | {np.median(e[:, 1]):.2f} | "
                f"{1000 * cpu.get(name, 0.0) / len(e):.0f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
