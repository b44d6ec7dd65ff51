"""Two-view pairs of the classical backbone with each feature / matcher setting, on builds.

    python benchmarks/matching.py SCENE [SCENE ...] [--frames 12] [--methods NAME ...]

Pairs: ``--frames`` evenly spaced query frames of each scene's default build (320x240, built when
missing), each with the 10 database images the VLAD index finds most similar (what the pipeline's
retrieval starts from; some have no true overlap). Each method is the classical backbone's
:meth:`~vgpnav_env.perception.backbones.classical.ClassicalBackbone.relative_pose` with one
:class:`~vgpnav_env.perception.backbones.classical.ClassicalConfig` (features extracted once per
image and method, not timed per pair), given the pair's images as the pipeline does (XFeat matches
are refined on them; ``xfeat-lg-unrefined`` without). A pair passes when the backbone accepts it;
a passed pair is right when its rotation is within 5 deg and its translation direction within 10
deg of the truth (the runs' poses, read here for evaluation only). Columns: passed right / wrong
per pair, frames with at least 3 right pairs (enough for motion averaging), the median number of
RANSAC inliers of right pairs, and CPU ms per pair (matching + two-view) and per image
(extraction), one process.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from vgpnav_env.build import build_runs, default_build_dir
from vgpnav_env.geometry import invert_pose, rotation_angle
from vgpnav_env.perception.backbones.classical import ClassicalBackbone, ClassicalConfig
from vgpnav_env.perception.backbones.threads import configure_threads
from vgpnav_env.perception.database import DatabaseConfig, open_database
from vgpnav_env.runs import load_build

BASE = ClassicalConfig(threads=1, fallback_pairs=0)
XFEAT_1024 = replace(BASE, features="xfeat", xfeat_keypoints=1024)
METHODS: dict[str, ClassicalConfig] = {
    "rootsift": BASE,
    "rootsift-c0.0005": replace(BASE, sift_contrast_threshold=0.0005),
    "xfeat1024-nn": replace(XFEAT_1024, ratio=0.9),
    "xfeat1024-lg": replace(XFEAT_1024, matcher="lighterglue"),
    "xfeat-lg": replace(BASE, features="xfeat", matcher="lighterglue"),
    "xfeat1024-lg-1.5px": replace(XFEAT_1024, matcher="lighterglue", xfeat_max_epipolar_error=1.5),
    "xfeat1024-x2-lg": replace(XFEAT_1024, matcher="lighterglue", xfeat_upscale=2.0),
    "xfeat-lg-unrefined": replace(BASE, features="xfeat", matcher="lighterglue", refine_window=0),
}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("scenes", nargs="+")
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    args = parser.parse_args()
    configure_threads(1)
    print(
        "| scene | method | right / pair | wrong / pair | frames >= 3 right | inliers (right) "
        "| CPU ms / pair | CPU ms / image |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for scene in args.scenes:
        path = default_build_dir(scene)
        if not (path / "query").is_dir():
            build_runs(scene, path)
        build = load_build(path)
        db = open_database(path, DatabaseConfig(prior="none"))
        camera = db.camera
        frames = np.unique(np.linspace(0, len(build.query) - 1, args.frames).round().astype(int))
        pairs = {int(f): np.argsort(-db.index.similarity(build.query.images[f]))[:10] for f in frames}
        for name in args.methods:
            backbone = ClassicalBackbone(METHODS[name])
            right = wrong = images = 0
            good_frames, inliers = 0, []
            extract_cpu = pair_cpu = 0.0
            cache: dict[int, object] = {}
            for f, refs in pairs.items():
                t0 = time.process_time()
                fq = backbone.extract(build.query.images[f])
                images += 1
                for i in refs:
                    if int(i) not in cache:
                        cache[int(i)] = backbone.extract(db.images[i])
                        images += 1
                extract_cpu += time.process_time() - t0
                frame_right = 0
                for i in refs:
                    t0 = time.process_time()
                    pair_images = (build.query.images[f], db.images[i])
                    pair, n_inliers, _ = backbone.relative_pose(fq, cache[int(i)], camera, images=pair_images)
                    pair_cpu += time.process_time() - t0
                    if pair is None:
                        continue
                    T_rq = invert_pose(db.poses[i]) @ build.query.poses[f]
                    t_true = T_rq[:3, 3] / max(np.linalg.norm(T_rq[:3, 3]), 1e-9)
                    ok = np.degrees(rotation_angle(pair.R, T_rq[:3, :3])) <= 5.0
                    ok &= np.degrees(np.arccos(np.clip(pair.t @ t_true, -1.0, 1.0))) <= 10.0
                    right, wrong = right + int(ok), wrong + int(not ok)
                    frame_right += int(ok)
                    if ok:
                        inliers.append(n_inliers)
                good_frames += int(frame_right >= 3)
            n_pairs = 10 * len(pairs)
            print(
                f"| {scene} | {name} | {right / n_pairs:.2f} | {wrong / n_pairs:.2f} | "
                f"{good_frames}/{len(pairs)} | {np.median(inliers) if inliers else 0:.0f} | "
                f"{1000 * pair_cpu / n_pairs:.0f} | {1000 * extract_cpu / images:.0f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
