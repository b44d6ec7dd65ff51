"""The classical backbone's scene check on builds: the shares of the database's own pairs each
matcher gets right, and what the check chooses (``vgpnav_env/perception/feature_choice.py``).

    python benchmarks/scene_check.py SCENE_OR_BUILD_DIR [...] [--size 320x240] [--both]

A scene (``home``, ``home:2``, a mesh directory) means its default build at ``--size`` (built when
missing). ``--both`` also measures XFeat + LighterGlue where the check does not need it. One
thread; CPU seconds per scene.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from vgpnav_env.arguments import size_arg
from vgpnav_env.build import build_runs, default_build_dir
from vgpnav_env.perception.backbones import ClassicalConfig
from vgpnav_env.perception.backbones.threads import configure_threads
from vgpnav_env.perception.database import DatabaseConfig, open_database
from vgpnav_env.perception.feature_choice import choose_features, pair_outcomes, sign_test


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("scenes", nargs="+")
    parser.add_argument("--size", type=size_arg, default=(320, 240))
    parser.add_argument("--both", action="store_true", help="measure XFeat + LighterGlue everywhere")
    args = parser.parse_args()
    configure_threads(1)
    config = ClassicalConfig(threads=1)
    print("| scene | RootSIFT | XFeat + LighterGlue (sign test) | chosen | pairs | CPU s |")
    print("|---|---|---|---|---|---|")
    for scene in args.scenes:
        path = (
            Path(scene) if (Path(scene) / "summary.json").is_file() else default_build_dir(scene, args.size)
        )
        if not (path / "summary.json").is_file():
            build_runs(scene, path, size=args.size)
        db = open_database(path, DatabaseConfig(prior="none"))
        t0 = time.process_time()
        choice = choose_features(db, config)
        xfeat, p = choice.xfeat, choice.p
        if xfeat is None and args.both:
            outcomes = pair_outcomes(db, config.switch_config())
            xfeat, p = float(outcomes.mean()), sign_test(pair_outcomes(db, config), outcomes)
        shown = "not tried" if xfeat is None else f"{xfeat:.2f} (p {p:.2g})"
        print(
            f"| {scene} | {choice.rootsift:.2f} | {shown} | {choice.features} | {choice.n_pairs} | "
            f"{time.process_time() - t0:.1f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
