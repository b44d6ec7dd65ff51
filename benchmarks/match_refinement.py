"""XFeat + LighterGlue matches refined by Lucas-Kanade: correspondence error and two-view poses.

    python benchmarks/match_refinement.py BUILD [--frames 40] [--windows 7 9 11] [--features xfeat]
        [--errors 0.5 1.0]

Pairs: ``--frames`` evenly spaced query frames of a build, each with the 10 database images the
VLAD index finds most similar. For every pair the backbone's putative matches are taken as they
are (window 0) and with their reference points refined by
:func:`~vgpnav_env.perception.backbones.classical.refine_matches` at each window. Columns:

- correspondence error: for the matches whose reference point lies within 4 px of the true
  correspondence (the query keypoint back-projected with the rendered query depth and moved by the
  true relative pose; read here for evaluation only), the median and 90th percentile of that
  distance (pixels), before and after the refinement;
- poses: poselib's 5-point LO-RANSAC on the matches as the backbone runs it (its Sampson bound and
  iteration limits); accepted = at least ``min_inliers`` inliers; right = rotation within 5 deg and
  translation direction within 10 deg of the truth; tight = within 2 deg and 5 deg; the median
  rotation and direction errors of the accepted pairs; ``--errors``: the Sampson bounds (pixels)
  to run RANSAC with, one row each (default: the backbone's for the features);
- CPU ms per pair of the refinement (one thread).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import poselib

from vgpnav_env.geometry import invert_pose, rotation_angle
from vgpnav_env.perception.backbones.classical import (
    ClassicalBackbone,
    ClassicalConfig,
    poselib_camera,
    refine_matches,
)
from vgpnav_env.perception.backbones.threads import configure_threads
from vgpnav_env.perception.database import DatabaseConfig, open_database
from vgpnav_env.runs import load_build, load_run_depth


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("build", type=Path)
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--windows", type=int, nargs="+", default=[7, 9, 11])
    parser.add_argument("--features", choices=["xfeat", "rootsift"], default="xfeat")
    parser.add_argument("--errors", type=float, nargs="+", help="Sampson bounds (px), one row each")
    args = parser.parse_args()
    configure_threads(1)
    config = ClassicalConfig(threads=1, fallback_pairs=0)
    if args.features == "xfeat":
        config = replace(config, features="xfeat", matcher="lighterglue")
    default = config.xfeat_max_epipolar_error if args.features == "xfeat" else config.max_epipolar_error
    bounds = args.errors or [default]
    backbone = ClassicalBackbone(config)
    build = load_build(args.build)
    db = open_database(args.build, DatabaseConfig(prior="none"))
    camera, K = db.camera, db.camera.K
    cam = poselib_camera(camera)
    depth = load_run_depth(args.build / "query")
    frames = np.unique(np.linspace(0, len(build.query) - 1, args.frames).round().astype(int))
    windows = [0, *args.windows]
    rows = [(w, b) for w in windows for b in bounds]
    errors: dict[int, list[float]] = {w: [] for w in windows}
    poses: dict[tuple[int, float], list[tuple[int, float, float]]] = {row: [] for row in rows}
    cpu = dict.fromkeys(windows, 0.0)
    cache: dict[int, object] = {}
    for f in frames:
        query = build.query.images[f]
        fq = backbone.extract(query)
        for i in np.argsort(-db.index.similarity(query))[:10]:
            i = int(i)
            fr = cache.setdefault(i, backbone.extract(db.images[i]))
            matches = backbone.match(fq, fr)
            if len(matches) < 5:
                continue
            pq, pr = fq.keypoints[matches[:, 0]], fr.keypoints[matches[:, 1]]
            T_rq = invert_pose(db.poses[i]) @ build.query.poses[f]
            pixel = np.clip(np.round(pq).astype(int), 0, [camera.width - 1, camera.height - 1])
            d = depth[f][pixel[:, 1], pixel[:, 0]]
            X = (np.c_[pq, np.ones(len(pq))] @ np.linalg.inv(K).T) * d[:, None] @ T_rq[:3, :3].T + T_rq[:3, 3]
            truth = (X @ K.T)[:, :2] / X[:, 2:3]
            correct = (d > 0) & (np.linalg.norm(pr - truth, axis=1) < 4.0)
            direction = T_rq[:3, 3] / max(np.linalg.norm(T_rq[:3, 3]), 1e-9)
            for w in windows:
                t0 = time.process_time()
                moved = refine_matches(query, db.images[i], pq, pr, w) if w else pr
                cpu[w] += time.process_time() - t0
                errors[w] += list(np.linalg.norm(moved - truth, axis=1)[correct])
                for b in bounds:
                    options = {
                        "max_epipolar_error": b,
                        "min_iterations": config.ransac_min_iterations,
                        "max_iterations": config.ransac_max_iterations,
                    }
                    pose, info = poselib.estimate_relative_pose(pq, moved, cam, cam, options, {})
                    t = np.asarray(pose.t) / max(np.linalg.norm(pose.t), 1e-12)
                    poses[w, b].append(
                        (
                            int(np.sum(info["inliers"])),
                            float(np.degrees(rotation_angle(np.asarray(pose.R), T_rq[:3, :3]))),
                            float(np.degrees(np.arccos(np.clip(t @ direction, -1.0, 1.0)))),
                        )
                    )
    print(f"{args.build.name}, {args.features}, {len(frames)} frames, {len(poses[rows[0]])} pairs\n")
    print(
        "| window | Sampson bound (px) | correspondence error median / p90 (px) | accepted | right | tight "
        "| rotation / direction error (deg) | CPU ms / pair |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for w, b in rows:
        e, p = np.array(errors[w]), np.array(poses[w, b])
        accepted = p[:, 0] >= config.min_inliers
        right = accepted & (p[:, 1] <= 5.0) & (p[:, 2] <= 10.0)
        tight = accepted & (p[:, 1] <= 2.0) & (p[:, 2] <= 5.0)
        print(
            f"| {w or 'none'} | {b:g} | {np.median(e):.2f} / {np.percentile(e, 90):.2f} | {accepted.sum()} "
            f"| {right.sum()} | {tight.sum()} "
            f"| {np.median(p[accepted, 1]):.2f} / {np.median(p[accepted, 2]):.2f} "
            f"| {1000 * cpu[w] / len(p):.1f} |"
        )


if __name__ == "__main__":
    main()
