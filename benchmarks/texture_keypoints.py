"""Median default-SIFT keypoint count per run and texture level (prints numbers; not a test).

    python benchmarks/texture_keypoints.py [--scenes home hospital] [--frames 9] [--size 320 240]
        [--levels rich realistic sparse] [--save-median-frames docs]

For each scene the database and query trajectories are built once (seed 0, at a tiny image size:
trajectories do not depend on it), then ``--frames`` evenly spaced frames of each run are rendered
at ``--size`` with each texture level and counted with ``cv2.SIFT_create()`` (default parameters) on
the grey image, exactly as ``tests/test_build.py::test_sift_keypoints_at_default_size`` does. The
benchmark target is a median >= 200 at 320x240 with the ``realistic`` level.
``--save-median-frames DIR`` writes the median-count frame of each run (realistic level) as
``DIR/<scene>_<run>.png``.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import cv2
import numpy as np

from vgpnav_env.build import build_runs
from vgpnav_env.geometry import PinholeCamera
from vgpnav_env.render import MujocoRenderer
from vgpnav_env.runs import load_build
from vgpnav_env.scenes import TEXTURE_LEVELS, load_scene, scene_slug


def count_keypoints(
    source: str, layout: str, poses: np.ndarray, camera: PinholeCamera, texture: str
) -> tuple[list[int], list[np.ndarray]]:
    """Default-SIFT keypoint counts and the RGB images of ``poses`` (T_wc, N x 4 x 4)."""
    sift = cv2.SIFT_create()
    counts, images = [], []
    with MujocoRenderer(load_scene(source, layout=layout, texture=texture), camera) as renderer:
        for T_wc in poses:
            rgb = renderer.render(T_wc).rgb
            counts.append(len(sift.detect(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))))
            images.append(rgb)
    return counts, images


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["home", "hospital"])
    parser.add_argument("--frames", type=int, default=9)
    parser.add_argument("--size", type=int, nargs=2, default=(320, 240), metavar=("W", "H"))
    parser.add_argument("--levels", nargs="+", default=list(TEXTURE_LEVELS), choices=TEXTURE_LEVELS)
    parser.add_argument("--save-median-frames", type=Path, default=None, metavar="DIR")
    args = parser.parse_args()
    camera = PinholeCamera(args.size[0], args.size[1], np.deg2rad(60.0))
    print(f"{'scene':<12} {'run':<9} {'texture':<10} median  counts")
    with tempfile.TemporaryDirectory() as tmp:
        for source in args.scenes:
            out = Path(tmp) / scene_slug(source)
            build_runs(source, out, size=(32, 24), seed=0, progress=False)
            build = load_build(out)
            for run in (build.database, build.query):
                kind, layout = run.metadata["kind"], run.metadata["layout"]
                idx = np.linspace(0, len(run) - 1, args.frames).round().astype(int)
                for level in args.levels:
                    counts, images = count_keypoints(source, layout, run.poses[idx], camera, level)
                    median = float(np.median(counts))
                    print(f"{source:<12} {kind:<9} {level:<10} {median:6.0f}  {counts}", flush=True)
                    if args.save_median_frames is not None and level == "realistic":
                        pick = int(np.argmin(np.abs(np.asarray(counts) - median)))
                        args.save_median_frames.mkdir(parents=True, exist_ok=True)
                        path = args.save_median_frames / f"{scene_slug(source)}_{kind}.png"
                        cv2.imwrite(str(path), cv2.cvtColor(images[pick], cv2.COLOR_RGB2BGR))


if __name__ == "__main__":
    main()
