"""Quality and speed of the classical backbone's dense query depth on a build's query run.

    python benchmarks/dense_depth.py [--scene home] [--queries 50] [--retrieval topk] [--verbose]

Runs the VGP-Nav pipeline (classical backbone, k = 10, no prior) on evenly spaced query frames of
the default 320x240 build of ``--scene`` (built on first use, minutes), exactly as
``vgpnav eval perception`` does, and scores the backbone's query depth of every localized frame
against the renderer's depth (read here for evaluation only). Pixels count when their true depth
is at most ``--max-depth`` metres and, for the predicted side, their depth confidence is at least
the pipeline's ``OccupancyConfig.min_confidence``:

- ``coverage``: confident pixels / true pixels;
- ``outliers``: fraction of confident pixels whose depth, scaled by the frame's optimal scale
  (median true / predicted), is off by more than 10 % (``outliers_20``: 20 %);
- ``rel_median``: median relative error of the confident pixels at that scale;
- ``shape_acc`` / ``shape_comp``: Acc / Comp (metres, eval/perception_runs.accuracy_completeness)
  of the confident points (every ``point_stride``-th pixel, as the pipeline) at the optimal scale
  and the TRUE pose, i.e. the dense depth's own share of the perception error;
- ``acc`` / ``comp``: the same with the pipeline's metric scale (true pose);
- ``seconds``: the backbone's ``plane_sweep`` time per frame (median; machine load matters).

Averages are over frames (as the evaluation). ``--verbose`` prints every frame.
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np

from vgpnav_env.build import build_runs, default_build_dir
from vgpnav_env.eval.perception_runs import accuracy_completeness
from vgpnav_env.perception.backbones import make_backbone
from vgpnav_env.perception.database import DatabaseConfig, open_database
from vgpnav_env.perception.occupancy import OccupancyConfig
from vgpnav_env.perception.pipeline import Perceiver, PerceptionConfig
from vgpnav_env.runs import load_build, load_run_depth


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--scene", default="home")
    parser.add_argument("--queries", type=int, default=50)
    parser.add_argument("--retrieval", default="topk", choices=("topk", "geometry"))
    parser.add_argument("--max-depth", type=float, default=5.0)
    parser.add_argument("--verbose", action="store_true")
    args = parser.parse_args()

    path = default_build_dir(args.scene, (320, 240), 0, "realistic")
    if not (path / "query").is_dir():
        build_runs(args.scene, path)
    build = load_build(path)
    db = open_database(path, DatabaseConfig(prior="none"))
    query, depth = build.query, load_run_depth(path / "query")
    frames = np.unique(np.linspace(0, len(query) - 1, args.queries).round().astype(int))
    occupancy = OccupancyConfig()
    config = PerceptionConfig.ablation(
        retrieval=args.retrieval, camera_height=float(query.poses[frames[0]][2, 3])
    )
    perceiver = Perceiver(db, make_backbone("classical", database=db), config=config)
    perceiver.initialize(query.images[frames[0]])
    camera, s = query.camera, occupancy.point_stride
    stride = np.zeros((camera.height, camera.width), bool)
    stride[::s, ::s] = True
    rng = np.random.default_rng(0)
    rows = []
    for f in frames:
        result = perceiver.perceive(query.images[f])
        out = result.backbone
        if not result.localized or out is None:
            continue
        true = depth[f]
        in_range = np.isfinite(true) & (true > 0) & (true <= args.max_depth)
        pred, conf = out.query_depth, out.query_depth_confidence
        confident = in_range & (pred > 0) & (conf >= occupancy.min_confidence)
        if confident.sum() < 10:
            continue
        best = float(np.median(true[confident] / pred[confident]))
        rel = np.abs(pred[confident] * best - true[confident]) / true[confident]
        gt = camera.backproject_world(true, query.poses[f], in_range)
        scores = []
        for scale in (best, result.scale):
            metric = (pred * scale).astype(np.float32)
            points = camera.backproject_world(
                metric, query.poses[f], confident & stride & (metric <= args.max_depth)
            )
            scores.extend(accuracy_completeness(points, gt, rng))
        row = {
            "frame": int(f),
            "coverage": confident.sum() / in_range.sum(),
            "outliers": float(np.mean(rel > 0.1)),
            "outliers_20": float(np.mean(rel > 0.2)),
            "rel_median": float(np.median(rel)),
            "shape_acc": scores[0],
            "shape_comp": scores[1],
            "acc": scores[2],
            "comp": scores[3],
            "seconds": out.timings.get("plane_sweep", float("nan")),
        }
        rows.append(row)
        if args.verbose:
            print(" ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()))
    summary = {k: float(np.nanmean([r[k] for r in rows])) for k in rows[0] if k not in ("frame", "seconds")}
    summary["seconds_median"] = float(np.median([r["seconds"] for r in rows]))
    summary["frames"] = len(rows)
    summary["queries"] = len(frames)
    summary["load_average_1min"] = os.getloadavg()[0]
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
