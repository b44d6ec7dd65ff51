"""Stage 4's metric centre against its resection, per frame, on builds.

    python benchmarks/resection.py SCENE_OR_BUILD_DIR [...]

Every query frame of each scene's default 320x240 build (built when missing), with the references
tracking chooses around the frame's true camera pose, one backbone round, motion averaging and
stage 4's scale (as in ``benchmarks/metric_centre.py``). The frame's pose is the metric centre,
then :func:`~vgpnav_env.perception.resection.resect` of it with the default settings and with each
``--min-angles`` triangulation angle. The truth is read for evaluation only. Columns: frames
within 5 cm / 5 deg, median centre error, and frames the resection moved more than 2 cm away from
or towards the truth.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np

from vgpnav_env.build import build_runs, default_build_dir
from vgpnav_env.eval.perception_runs import QuerySetup
from vgpnav_env.geometry import rotation_angle
from vgpnav_env.perception.backbones.threads import configure_threads
from vgpnav_env.perception.motion_averaging import metric_centre
from vgpnav_env.perception.pipeline import Clock, Perceiver, PerceptionConfig
from vgpnav_env.perception.recovery import Frame
from vgpnav_env.perception.resection import ResectionConfig, resect
from vgpnav_env.perception.retrieval import tracked_references
from vgpnav_env.perception.scale_recovery import GroundAnchor
from vgpnav_env.perception.verify import check_scale


def pose_errors(build: Path, configs: list[ResectionConfig]) -> np.ndarray:
    """(frames, 1 + len(configs), 2) centre error (m) and rotation error (deg): the metric
    centre's pose, then each resection's (the metric centre's where the resection did not stand)."""
    worker = QuerySetup(build, "classical", {}, 0)()
    query, db = worker.build.query, worker.database
    config = replace(PerceptionConfig(), camera_height=float(query.poses[0][2, 3]), resection=None)
    perceiver = Perceiver(db, worker.backbone, config=config)
    anchor = GroundAnchor(config.scale)  # the true floor under the first query frame
    anchor.initialize([(query.poses[0], None)], config.camera_height)
    rows = []
    for i in range(len(query.images)):
        T_true = query.poses[i]
        sims = np.nan_to_num(db.index.similarity(query.images[i]), nan=-1.0)
        refs = tracked_references(sims, db.poses, T_true, perceiver.camera, config.retrieval, config.tracking)
        out, motion = perceiver.round(Frame(query.images[i], None, None, T_true, None, Clock()), refs)
        if not motion.ok or motion.reason == "single reference":
            continue
        T, ray_scale = motion.T_wq, motion.scale_from_rays
        ground = perceiver.ground(out, T, anchor.expected_height_b(T, ray_scale))
        if not ground.found:
            ground = perceiver.ground(out, T, None)
        estimate = anchor.scale_for(T, ground, fallback_scale=ray_scale)
        estimate = check_scale(estimate, ray_scale, config.verify, float(motion.weights.sum()), ground)
        if not estimate.ok:
            continue
        T_wi = db.poses[refs]
        centre = metric_centre(motion, T_wi, out.T_iq, estimate.scale, out.scale_valid, config.averaging)
        poses = [centre]
        for c in configs:
            resected = resect(centre, T_wi, out.matches, perceiver.camera, c).T_wq
            poses.append(centre if resected is None else resected)
        rows.append(
            [
                (
                    np.linalg.norm(P[:3, 3] - T_true[:3, 3]),
                    np.degrees(rotation_angle(P[:3, :3], T_true[:3, :3])),
                )
                for P in poses
            ]
        )
    return np.array(rows).reshape(-1, 1 + len(configs), 2)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("scenes", nargs="+")
    parser.add_argument("--min-angles", type=float, nargs="*", default=[1.0, 2.0, 3.0])
    args = parser.parse_args()
    configure_threads(1)
    configs = [ResectionConfig(), *(ResectionConfig(min_angle_deg=a) for a in args.min_angles)]
    names = [
        "metric centre",
        "resection (default)",
        *(f"resection, min_angle_deg {a:g}" for a in args.min_angles),
    ]
    header = ["scene", "frames", "pose", "within 5 cm / 5 deg", "median (m)", "away > 2 cm", "closer > 2 cm"]
    print("| " + " | ".join(header) + " |")
    print("|---|---|---|---|---|---|---|")
    for scene in args.scenes:
        path = Path(scene)
        if not (path / "summary.json").is_file():
            path = default_build_dir(scene, (320, 240))
        if not (path / "summary.json").is_file():
            build_runs(scene, path, size=(320, 240))
        e = pose_errors(path, configs)
        for j, name in enumerate(names):
            right = np.mean((e[:, j, 0] < 0.05) & (e[:, j, 1] < 5.0))
            shift = e[:, j, 0] - e[:, 0, 0]
            print(
                f"| {scene} | {len(e)} | {name} | {right:.3f} | {np.median(e[:, j, 0]):.4f} | "
                f"{(shift > 0.02).sum()} | {(shift < -0.02).sum()} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
