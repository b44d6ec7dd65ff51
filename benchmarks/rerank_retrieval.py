"""Retrieval recall of geometric re-ranking settings, retrieval alone (no backbone), on a build.

    python benchmarks/rerank_retrieval.py [--scene hospital] [--pools 20 40 80] [--keypoints 600 300]

Per query frame of the scene's default 320x240 build: VLAD similarity, then for each setting
(``RetrievalConfig.rerank`` candidates x ``rerank_keypoints``) :func:`geometric_rerank` and
Alg. 1 (:func:`select_references`, k = 10). Retrieval recall: a chosen reference within 1 m / 45
deg of the true pose (``RETRIEVAL_HIT`` of the reports); best-reference hit: the first chosen one
is. CPU: process seconds of ``geometric_rerank`` per frame (single thread). Query poses are read
for evaluation only. Measured on main at 738a134 (load 8-10 on 2 cores; one pass of 80
candidates, the other pools scaled by the candidates: the cost per candidate is constant):

| setting | hospital retrieval recall | hospital:1 retrieval recall | CPU s/frame (hospital) |
|---|---|---|---|
| VLAD only | 0.876 | 0.894 | 0 |
| rerank 20, 600 keypoints | 0.903 | 0.885 | ~0.10 |
| rerank 40, 600 keypoints | 0.912 | 0.876 | ~0.20 |
| rerank 80, 600 keypoints | 0.921 | 0.870 | 0.39 |
| rerank 20, 300 keypoints | 0.888 | - | ~0.06 |
| rerank 40, 300 keypoints | 0.903 | - | ~0.12 |
| rerank 80, 300 keypoints | 0.900 | - | 0.24 |

40 / 600 gives the retrieval recall of ``vgpnav eval localization ... --rerank 40`` on both scenes.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from vgpnav_env.build import build_runs, default_build_dir
from vgpnav_env.eval.perception_runs import RETRIEVAL_HIT, retrieval_hit
from vgpnav_env.perception.backbones.classical import rootsift
from vgpnav_env.perception.database import DatabaseConfig, open_database
from vgpnav_env.perception.retrieval import RetrievalConfig, geometric_rerank, select_references
from vgpnav_env.runs import load_build


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--scene", default="hospital")
    parser.add_argument("--pools", type=int, nargs="+", default=[20, 40, 80])
    parser.add_argument("--keypoints", type=int, nargs="+", default=[600, 300])
    args = parser.parse_args()
    path = default_build_dir(args.scene, (320, 240), 0, "realistic")
    if not (path / "query").is_dir():
        build_runs(args.scene, path)
    query = load_build(path).query
    db = open_database(path, DatabaseConfig(prior="none"))
    sift = db.index.sift
    settings = {"VLAD only": RetrievalConfig()} | {
        f"rerank {n}, {m} keypoints": RetrievalConfig(rerank=n, rerank_keypoints=m)
        for m in args.keypoints
        for n in args.pools
    }
    hits = {name: [] for name in settings}
    first = {name: [] for name in settings}
    cpu = dict.fromkeys(settings, 0.0)
    for i, image in enumerate(query.images):
        similarity = np.nan_to_num(db.index.similarity(image), nan=-1.0)
        features = rootsift(image, sift)
        for name, config in settings.items():
            t0 = time.process_time()
            s = geometric_rerank(similarity, features, db.reference_features, config, sift.ratio)
            cpu[name] += time.process_time() - t0
            refs = select_references(s, db.poses, config)
            hits[name].append(retrieval_hit(refs, db.poses, query.poses[i]))
            first[name].append(retrieval_hit(refs[:1], db.poses, query.poses[i]))
    n = len(query.images)
    print(
        f"{args.scene}: {n} queries; hit = a reference within {RETRIEVAL_HIT[0]} m / {RETRIEVAL_HIT[1]} deg"
    )
    print("| setting | retrieval recall | best-reference hit | CPU s/frame |\n|---|---|---|---|")
    for name in settings:
        print(f"| {name} | {np.mean(hits[name]):.3f} | {np.mean(first[name]):.3f} | {cpu[name] / n:.3f} |")


if __name__ == "__main__":
    main()
