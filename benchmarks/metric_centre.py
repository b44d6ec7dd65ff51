"""Camera centres from rays alone against the metric centre, per ``distance_sigma``, on builds.

    python benchmarks/metric_centre.py SCENE_OR_BUILD_DIR [...] [--stride 1] [--sigmas 0.1 0.2 0.3 0.5 1.0]

Every ``--stride``-th query frame of each scene's default 320x240 build (built when missing), with
the references tracking chooses around the frame's true camera pose, one backbone round and motion
averaging (the pipeline's stage 2-3, :meth:`~vgpnav_env.perception.pipeline.Perceiver.round`).
Frames whose averaging fails or places a single reference are left out. Each frame's centre is
taken from the rays (the averaged pose) and from
:func:`~vgpnav_env.perception.motion_averaging.metric_centre` at each ``distance_sigma``, with stage
4's scale: the ground peak scaled to the camera's height above a floor anchored under the first
query frame, checked against the rays' own scale. The truth is read for evaluation only (and for
the anchor). Columns: median centre error, share of frames within 2 cm and within 5 cm.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

import numpy as np

from vgpnav_env.build import build_runs, default_build_dir
from vgpnav_env.eval.perception_runs import QuerySetup
from vgpnav_env.geometry import PinholeCamera
from vgpnav_env.perception.backbones.base import BackboneOutput
from vgpnav_env.perception.backbones.threads import configure_threads
from vgpnav_env.perception.motion_averaging import MotionAveragingConfig, MotionResult, metric_centre
from vgpnav_env.perception.pipeline import Clock, Perceiver, PerceptionConfig
from vgpnav_env.perception.recovery import Frame
from vgpnav_env.perception.resection import ResectionConfig, resect
from vgpnav_env.perception.retrieval import tracked_references
from vgpnav_env.perception.scale_recovery import GroundAnchor
from vgpnav_env.perception.verify import check_scale


class StageFourFrame(NamedTuple):
    """One query frame at stage 4: its true pose (evaluation only), the references' poses, the
    backbone output and motion averaging over them, stage 4's metric scale and the camera."""

    T_true: np.ndarray
    T_wi: np.ndarray
    out: BackboneOutput
    motion: MotionResult
    scale: float
    camera: PinholeCamera

    def centre(self, averaging: MotionAveragingConfig | None = None) -> np.ndarray:
        """Stage 4's metric centre of the frame (``T_wc``), default averaging settings unless given."""
        return metric_centre(
            self.motion,
            self.T_wi,
            self.out.T_iq,
            self.scale,
            self.out.scale_valid,
            averaging or MotionAveragingConfig(),
        )

    def resected(self, T_wc: np.ndarray, config: ResectionConfig) -> np.ndarray:
        """``T_wc`` refined by stage 4's resection (itself where the resection does not stand)."""
        found = resect(T_wc, self.T_wi, self.out.matches, self.camera, config).T_wq
        return T_wc if found is None else found


def stage_four_frames(build: Path, stride: int = 1) -> Iterator[StageFourFrame]:
    """Every ``stride``-th query frame of ``build`` whose motion averaging places more than one
    reference and whose stage 4 scale checks out, with the references tracking chooses around its
    true camera pose, one backbone round and motion averaging (the pipeline's stages 2-3,
    :meth:`~vgpnav_env.perception.pipeline.Perceiver.round`)."""
    worker = QuerySetup(build, "classical", {}, 0)()
    query, db = worker.build.query, worker.database
    config = replace(PerceptionConfig(), camera_height=float(query.poses[0][2, 3]))
    perceiver = Perceiver(db, worker.backbone, config=config)
    anchor = GroundAnchor(config.scale)  # the true floor under the first query frame
    anchor.initialize([(query.poses[0], None)], config.camera_height)
    for i in range(0, len(query.images), stride):
        T_true = query.poses[i]
        sims = np.nan_to_num(db.index.similarity(query.images[i]), nan=-1.0)
        refs = tracked_references(sims, db.poses, T_true, perceiver.camera, config.retrieval, config.tracking)
        frame = Frame(query.images[i], None, None, T_true, None, Clock())
        out, motion = perceiver.round(frame, refs)
        if not motion.ok or motion.reason == "single reference":
            continue
        # Stage 4's scale: the ground peak near the rays' scale at the camera's height above the
        # floor (the pose's height over the anchor), checked against the rays' own scale.
        T, ray_scale = motion.T_wq, motion.scale_from_rays
        ground = perceiver.ground(out, T, anchor.expected_height_b(T, ray_scale))
        if not ground.found:
            ground = perceiver.ground(out, T, None)
        estimate = anchor.scale_for(T, ground, fallback_scale=ray_scale)
        estimate = check_scale(estimate, ray_scale, config.verify, float(motion.weights.sum()), ground)
        if estimate.ok:
            yield StageFourFrame(T_true, db.poses[refs], out, motion, estimate.scale, perceiver.camera)


def scene_build(scene: str) -> Path:
    """A build directory as given, else the scene's default 320x240 build (built when missing)."""
    path = Path(scene)
    if not (path / "summary.json").is_file():
        path = default_build_dir(scene, (320, 240))
    if not (path / "summary.json").is_file():
        build_runs(scene, path, size=(320, 240))
    return path


def centre_errors(build: Path, stride: int, sigmas: list[float]) -> np.ndarray:
    """(frames, 1 + len(sigmas)) centre errors in metres: the rays', then each sigma's."""
    rows = []
    for f in stage_four_frames(build, stride):
        centres = [f.motion.T_wq[:3, 3]]
        for sigma in sigmas:
            centres.append(f.centre(MotionAveragingConfig(distance_sigma=sigma))[:3, 3])
        rows.append(np.linalg.norm(np.array(centres) - f.T_true[:3, 3], axis=1))
    return np.array(rows).reshape(-1, 1 + len(sigmas))


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("scenes", nargs="+")
    parser.add_argument("--stride", type=int, default=1)
    parser.add_argument("--sigmas", type=float, nargs="+", default=[0.1, 0.2, 0.3, 0.5, 1.0])
    args = parser.parse_args()
    configure_threads(1)
    print("| scene | frames | centre | median (m) | within 2 cm | within 5 cm |")
    print("|---|---|---|---|---|---|")
    for scene in args.scenes:
        errors = centre_errors(scene_build(scene), args.stride, args.sigmas)
        names = ["rays", *(f"metric, distance_sigma {s:g}" for s in args.sigmas)]
        for name, e in zip(names, errors.T, strict=True):
            print(
                f"| {scene} | {len(e)} | {name} | {np.median(e):.4f} | {(e < 0.02).mean():.3f} | "
                f"{(e < 0.05).mean():.3f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
