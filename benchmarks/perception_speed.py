"""Wall and CPU seconds per VGP-Nav module and per database-preparation step (issue 11 targets).

    python benchmarks/perception_speed.py [--build DIR] [--queries 20] [--threads 0 1] [--database]

Perception: the classical pipeline (k = 10, no prior) over ``--queries`` evenly spaced query frames
of the default 320x240 ``home`` build (built on first use), once per ``--threads`` value (0 = every
available core, 1 = serial; the results are the same). Per module the median wall seconds and the
median CPU seconds of the process (all threads) over the localized frames (the first frame only
warms up), beside the paper's Table VI (VGGT, RTX 5090). Targets: <= 0.25 s wall and <= 0.4 CPU s
per frame.

``--database``: the home database preparation from an empty cache (a copy of the database run in a
temporary directory): VLAD index, stored features and prior map, wall and CPU seconds per step.
Target: <= 45 s in all.

Wall seconds depend on what else runs on the cores: the load average is printed; compare CPU
seconds across machines and loads.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from vgpnav_env.build import build_runs, default_build_dir
from vgpnav_env.eval.perception_runs import query_subset
from vgpnav_env.eval.timing import PAPER_SECONDS
from vgpnav_env.perception.backbones import ClassicalConfig, make_backbone
from vgpnav_env.perception.database import Database, DatabaseConfig, open_database
from vgpnav_env.perception.pipeline import TIMING_KEYS, Perceiver, PerceptionConfig
from vgpnav_env.runs import load_build

SUB_STEPS = ("features", "two_view", "scale_linking", "plane_sweep")


def perception(build_dir: Path, n_queries: int, threads: int) -> None:
    build = load_build(build_dir)
    config = ClassicalConfig(threads=threads)
    db = open_database(build_dir, DatabaseConfig(prior="none"), backbone_config=config)
    query = build.query
    frames = query_subset(len(query), n_queries)
    perceiver = Perceiver(
        db,
        make_backbone("classical", database=db, config=config),
        config=PerceptionConfig(camera_height=float(query.poses[frames[0]][2, 3])),
    )
    perceiver.initialize(query.images[frames[0]])
    rows, lost = [], 0
    for f in frames[1:]:
        result = perceiver.perceive(query.images[f])
        if not result.localized:
            lost += 1
            continue
        sub = result.backbone.timings if result.backbone is not None else {}
        rows.append(result.timings | {f"backbone.{k}": v for k, v in sub.items()})

    def median(key: str) -> float:
        return float(np.median([r.get(key, np.nan) for r in rows]))

    print(f"\nthreads={threads}: {len(rows)} localized frames, {lost} lost, load {os.getloadavg()[0]:.1f}")
    print(f"{'module':18s} {'wall s':>8s} {'CPU s':>8s} {'paper s':>8s}")
    for key in TIMING_KEYS:
        cpu = median("cpu" if key == "total" else f"{key}_cpu")
        paper = PAPER_SECONDS.get(key)
        print(f"{key:18s} {median(key):8.3f} {cpu:8.3f} {'' if paper is None else f'{paper:8.3f}'}")
    for step in SUB_STEPS:
        wall, cpu = median(f"backbone.{step}"), median(f"backbone.{step}_cpu")
        print(f"  backbone.{step:14s} {wall:8.3f} {cpu:8.3f}")


def database_preparation(build_dir: Path) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp) / "database"
        shutil.copytree(build_dir / "database", run, ignore=shutil.ignore_patterns("index", "index-*"))
        t0, c0 = time.perf_counter(), time.process_time()
        db = Database.open(run, config=DatabaseConfig(), progress=False)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    steps = ("features", "index", "prior")
    print(f"\ndatabase preparation ({len(db)} images), load {os.getloadavg()[0]:.1f}")
    print(f"{'step':18s} {'wall s':>8s} {'CPU s':>8s}")
    for step in steps:
        print(f"{step:18s} {db.timings[step]:8.1f} {db.timings.get(f'{step}_cpu', np.nan):8.1f}")
    print(f"{'all (incl. loading)':18s} {wall:8.1f} {cpu:8.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--build", type=Path, help="a build directory (default: the home build)")
    parser.add_argument("--queries", type=int, default=20)
    parser.add_argument(
        "--threads", type=int, nargs="*", default=[0, 1], help="thread counts to time (none: skip perception)"
    )
    parser.add_argument("--database", action="store_true", help="also time the database preparation")
    args = parser.parse_args()
    build_dir = args.build or default_build_dir("home", (320, 240), 0, "realistic")
    if args.build is None:
        build_runs("home", build_dir)
    for threads in args.threads:
        perception(build_dir, args.queries, threads)
    if args.database:
        database_preparation(build_dir)


if __name__ == "__main__":
    main()
