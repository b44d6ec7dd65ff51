"""Stage 4's metric centre against its resection, per frame, on builds.

    python benchmarks/resection.py SCENE_OR_BUILD_DIR [...]

Every query frame of each scene's default 320x240 build (built when missing), with the references
tracking chooses around the frame's true camera pose, one backbone round, motion averaging and
stage 4's scale (``stage_four_frames`` of ``benchmarks/metric_centre.py``). The frame's pose is
the metric centre, then :func:`~vgpnav_env.perception.resection.resect` of it without its hybrid
step, with the default settings, with each ``--hybrid-px`` threshold of the hybrid step and with
each ``--min-angles`` triangulation angle. The truth is read for evaluation only. Columns: frames
within 5 cm / 5 deg, median centre error, frames the resection moved more than 2 cm away from or
towards the truth, and the resection's CPU per frame.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from metric_centre import scene_build, stage_four_frames

from vgpnav_env.eval.perception_runs import pose_errors
from vgpnav_env.perception.backbones.threads import configure_threads
from vgpnav_env.perception.resection import ResectionConfig


def frame_errors(
    build: Path, configs: list[ResectionConfig], stride: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """(frames, 1 + len(configs), 2) centre error (m) and rotation error (deg): the metric
    centre's pose, then each resection's (the metric centre's where the resection did not stand);
    and (1 + len(configs),) mean CPU milliseconds per frame of each resection (0 for the centre)."""
    rows, cpu = [], np.zeros(1 + len(configs))
    for f in stage_four_frames(build, stride):
        centre = f.centre()
        poses = [centre]
        for j, c in enumerate(configs, start=1):
            start = time.process_time()
            poses.append(f.resected(centre, c))
            cpu[j] += time.process_time() - start
        rows.append([pose_errors(P, f.T_true) for P in poses])
    return np.array(rows).reshape(-1, 1 + len(configs), 2), 1000.0 * cpu / max(len(rows), 1)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("scenes", nargs="+")
    parser.add_argument("--stride", type=int, default=1, help="every this many query frames")
    parser.add_argument("--hybrid-px", type=float, nargs="*", default=[0.5, 2.0])
    parser.add_argument("--min-angles", type=float, nargs="*", default=[1.0, 2.0, 3.0])
    args = parser.parse_args()
    configure_threads(1)
    configs = [
        ResectionConfig(hybrid_epipolar_px=None),
        ResectionConfig(),
        *(ResectionConfig(hybrid_epipolar_px=px) for px in args.hybrid_px),
        *(ResectionConfig(min_angle_deg=a) for a in args.min_angles),
    ]
    names = [
        "metric centre",
        "resection, no hybrid step",
        "resection (default)",
        *(f"resection, hybrid_epipolar_px {px:g}" for px in args.hybrid_px),
        *(f"resection, min_angle_deg {a:g}" for a in args.min_angles),
    ]
    header = ["scene", "frames", "pose", "within 5 cm / 5 deg", "median (m)", "away > 2 cm", "closer > 2 cm"]
    header.append("CPU ms / frame")
    print("| " + " | ".join(header) + " |")
    print("|---" * len(header) + "|")
    for scene in args.scenes:
        e, cpu_ms = frame_errors(scene_build(scene), configs, args.stride)
        for j, name in enumerate(names):
            right = np.mean((e[:, j, 0] < 0.05) & (e[:, j, 1] < 5.0))
            shift = e[:, j, 0] - e[:, 0, 0]
            print(
                f"| {scene} | {len(e)} | {name} | {right:.3f} | {np.median(e[:, j, 0]):.4f} | "
                f"{(shift > 0.02).sum()} | {(shift < -0.02).sum()} | {cpu_ms[j]:.1f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
