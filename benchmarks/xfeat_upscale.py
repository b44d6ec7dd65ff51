"""XFeat detected on an upscaled image: two-view poses of XFeat + LighterGlue pairs, per upscale.

    python benchmarks/xfeat_upscale.py BUILD [BUILD ...] [--upscales 1 1.5 2] [--frames 20]

Pairs: ``--frames`` evenly spaced query frames of each build, each with the 10 database images the
VLAD index finds most similar. For each ``ClassicalConfig.xfeat_upscale`` the backbone's XFeat +
LighterGlue pair (refined matches, its Sampson bound and ``min_inliers``) is accepted or not;
accepted pairs are right within 5 deg rotation and 10 deg translation direction of the truth
(the runs' poses, read here for evaluation only), tight within 2 deg and 5 deg. CPU: the query's
extraction and the pairs, per frame, one thread (the references' extraction is not counted: a
database stores it once).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from vgpnav_env.geometry import invert_pose, rotation_angle
from vgpnav_env.perception.backbones.classical import ClassicalBackbone, ClassicalConfig
from vgpnav_env.perception.backbones.threads import configure_threads
from vgpnav_env.perception.database import DatabaseConfig, open_database
from vgpnav_env.runs import load_build


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("builds", type=Path, nargs="+")
    parser.add_argument("--upscales", type=float, nargs="+", default=[1.0, 1.5, 2.0])
    parser.add_argument("--frames", type=int, default=20)
    args = parser.parse_args()
    configure_threads(1)
    base = replace(ClassicalConfig(threads=1, fallback_pairs=0), features="xfeat", matcher="lighterglue")
    print("| build | upscale | pairs | accepted | right | tight | median error rot. / dir. | CPU s / frame |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for build_dir in args.builds:
        build = load_build(build_dir)
        db = open_database(build_dir, DatabaseConfig(prior="none"))
        frames = np.unique(np.linspace(0, len(build.query) - 1, args.frames).round().astype(int))
        for upscale in args.upscales:
            backbone = ClassicalBackbone(replace(base, xfeat_upscale=upscale))
            references: dict[int, object] = {}
            pairs, right, tight, cpu, errors = 0, 0, 0, 0.0, []
            for f in frames:
                query = build.query.images[f]
                t0 = time.process_time()
                fq = backbone.extract(query)
                cpu += time.process_time() - t0
                for i in (int(i) for i in np.argsort(-db.index.similarity(query))[:10]):
                    fr = references.setdefault(i, backbone.extract(db.images[i]))
                    T_rq = invert_pose(db.poses[i]) @ build.query.poses[f]
                    direction = T_rq[:3, 3] / max(np.linalg.norm(T_rq[:3, 3]), 1e-9)
                    pairs += 1
                    t0 = time.process_time()
                    found, _, _ = backbone.relative_pose(fq, fr, db.camera, images=(query, db.images[i]))
                    cpu += time.process_time() - t0
                    if found is None:
                        continue
                    rotation = float(np.degrees(rotation_angle(found.R, T_rq[:3, :3])))
                    angle = float(np.degrees(np.arccos(np.clip(found.t @ direction, -1.0, 1.0))))
                    errors.append((rotation, angle))
                    right += rotation <= 5.0 and angle <= 10.0
                    tight += rotation <= 2.0 and angle <= 5.0
            e = np.array(errors).reshape(-1, 2)
            median = f"{np.median(e[:, 0]):.2f}° / {np.median(e[:, 1]):.2f}°" if len(e) else "-"
            print(
                f"| {build_dir.name} | {upscale:g} | {pairs} | {len(e)} | {right} | {tight} | {median} "
                f"| {cpu / len(frames):.2f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
