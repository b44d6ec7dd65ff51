"""Build a scene's database run (``base`` layout) and query run (``changed`` layout) on disk.

``build_runs(source)`` loads both layouts, plans a coverage trajectory on each layout's
ground-truth navigable grid (database: dense, camera 1.5 +- 0.1 m; query: sparser, its own
tour, camera 1.2 +- 0.05 m; pitch 15-30 deg down for both), renders every frame with one
MuJoCo renderer per layout and writes, atomically::

    <out>/database/   run (see vgpnav_env.runs), with groundtruth/depth.npz
    <out>/query/      run, with groundtruth/depth.npz
    <out>/summary.json

An existing build with the same parameters is reused. Read builds with
:func:`vgpnav_env.runs.load_build`.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from vgpnav_env.arguments import MAX_IMAGE_SIZE, seed_arg, size_arg
from vgpnav_env.geometry import PinholeCamera
from vgpnav_env.groundtruth import ground_truth_map
from vgpnav_env.render import MujocoRenderer
from vgpnav_env.robot import FOVY_DEG, ROBOT_HEIGHT, ROBOT_RADIUS
from vgpnav_env.runs import (
    BUILD_FORMAT,
    BUILD_VERSION,
    RUN_VERSION,
    Run,
    RunFormatError,
    atomic_directory,
    build_dir_name,
    check_replaceable,
    default_cache_dir,
    load_build,
    write_json,
    write_run,
)
from vgpnav_env.scenes import load_scene, scene_slug
from vgpnav_env.scenes.materials import MATERIALS_VERSION
from vgpnav_env.scenes.registry import BUILTIN_DIR
from vgpnav_env.scenes.scene import Scene
from vgpnav_env.trajectories import (
    DATABASE_HEIGHT,
    PITCH_RANGE_DEG,
    QUERY_HEIGHT,
    TRAJECTORY_VERSION,
    coverage_trajectory,
)

logger = logging.getLogger(__name__)

DEFAULT_SIZE = (320, 240)
#: Ground-truth grid used to plan trajectories (metres; robot radius / height of ``vgpnav_env.robot``).
GRID_RESOLUTION = 0.05
#: Trajectory parameters per run kind (keyword arguments of ``coverage_trajectory``).
TRAJECTORIES: dict[str, dict[str, Any]] = {
    "database": {
        "spacing": 0.3,
        "height": DATABASE_HEIGHT,
        "pitch_deg": PITCH_RANGE_DEG,
        "cover_spacing": 1.5,
        "max_turn_deg": 45.0,
        "look_around_prob": 1.0,
        "yaw_jitter_deg": 10.0,
    },
    "query": {
        "spacing": 0.5,
        "height": QUERY_HEIGHT,
        "pitch_deg": PITCH_RANGE_DEG,
        "cover_spacing": 2.5,
        "max_turn_deg": 45.0,
        "look_around_prob": 0.0,
        "yaw_jitter_deg": 20.0,
    },
}
LAYOUTS = {"database": "base", "query": "changed"}


def check_size(size: tuple[int, int]) -> tuple[int, int]:
    """Validate an image size (width, height): positive integers up to ``MAX_IMAGE_SIZE``."""
    try:
        w, h = size
    except (TypeError, ValueError) as e:
        raise ValueError(f"image size must be (width, height), got {size!r}") from e
    if not all(isinstance(v, int | np.integer) and not isinstance(v, bool) for v in (w, h)):
        raise ValueError(f"image size must be integers, got {size!r}")
    max_w, max_h = MAX_IMAGE_SIZE
    if not (0 < w <= max_w and 0 < h <= max_h):
        raise ValueError(f"image size {w}x{h} out of range: width 1-{max_w}, height 1-{max_h}")
    return int(w), int(h)


def check_seed(seed: int) -> int:
    """Validate a seed: a non-negative integer."""
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    return int(seed)


def default_build_dir(
    source: str, size: tuple[int, int] = DEFAULT_SIZE, seed: int = 0, texture: str = "realistic"
) -> Path:
    """``$VGPNAV_CACHE`` (or ``~/.cache/vgpnav``) / ``<scene_slug>-<W>x<H>-s<seed>-<texture>``."""
    return default_cache_dir() / build_dir_name(scene_slug(source), size, seed, texture)


def _source_digest(source: str) -> str | None:
    """SHA-256 of a spec file, a built-in's spec, or a mesh-scene directory's layouts and every file
    they reference (meshes, MTL, textures), so an edited source invalidates its builds; else None."""
    path = Path(source)
    if path.is_dir():
        from vgpnav_env.scenes.mesh_scene import mesh_scene_digest

        return mesh_scene_digest(path)
    if not path.is_file():
        path = BUILTIN_DIR / f"{source.partition(':')[0]}.yaml"
        if ":" in source or not path.is_file():
            return None
    return hashlib.sha256(path.read_bytes()).hexdigest()


def build_parameters(
    source: str, size: tuple[int, int], seed: int, texture: str, fovy_deg: float, query_lighting: str
) -> dict[str, Any]:
    """Everything that determines a build's content (compared to decide whether to reuse one)."""
    return {
        "source": str(source),
        "source_sha256": _source_digest(source),
        "width": size[0],
        "height": size[1],
        "seed": seed,
        "texture": texture,
        "fovy_deg": float(fovy_deg),
        "query_lighting": query_lighting,
        "layouts": dict(LAYOUTS),
        "trajectories": {
            k: {n: list(v) if isinstance(v, tuple) else v for n, v in t.items()}
            for k, t in TRAJECTORIES.items()
        },
        "trajectory_version": TRAJECTORY_VERSION,
        "run_format_version": RUN_VERSION,
        "build_version": BUILD_VERSION,
        "materials_version": MATERIALS_VERSION,
    }


def _reusable(out: Path, params: dict[str, Any]) -> dict[str, Any] | None:
    if not (out / "summary.json").is_file():
        return None
    try:
        build = load_build(out)
    except RunFormatError as e:
        logger.warning("rebuilding %s: existing build unreadable (%s)", out, e)
        return None
    if build.summary.get("parameters") != params:
        logger.info("rebuilding %s: parameters changed", out)
        return None
    return build.summary


def _render_run(
    scene: Scene, poses: np.ndarray, camera: PinholeCamera, bar: tqdm
) -> tuple[np.ndarray, np.ndarray]:
    images = np.empty((len(poses), camera.height, camera.width, 3), np.uint8)
    depth = np.empty((len(poses), camera.height, camera.width), np.float32)
    with MujocoRenderer(scene, camera) as renderer:
        for i, T_wc in enumerate(poses):
            frame = renderer.render(T_wc)
            images[i], depth[i] = frame.rgb, frame.depth
            bar.update(1)
    return images, depth


def build_runs(
    source: str,
    out_dir: Path | str | None = None,
    *,
    size: tuple[int, int] = DEFAULT_SIZE,
    seed: int = 0,
    texture: str = "realistic",
    fovy_deg: float = FOVY_DEG,
    query_lighting: str = "default",
    progress: bool = True,
) -> dict[str, Any]:
    """Render and save the database and query runs of scene ``source``; return the summary.

    ``source`` is a built-in scene name or a spec path (see ``vgpnav_env.scenes.load_scene``);
    ``size`` = (width, height) pixels; ``fovy_deg`` the vertical field of view; ``seed`` fixes
    both trajectories (same seed, same images and poses). ``out_dir`` defaults to
    :func:`default_build_dir`. Reuses an existing build with identical parameters. Nothing is
    left half-written on failure (temporary directory + rename).
    """
    size = check_size(tuple(size))
    seed = check_seed(seed)
    if not 1.0 <= fovy_deg <= 170.0:
        raise ValueError(f"fovy_deg must lie in [1, 170] degrees, got {fovy_deg}")
    out = Path(out_dir) if out_dir is not None else default_build_dir(source, size, seed, texture)
    params = build_parameters(source, size, seed, texture, fovy_deg, query_lighting)
    check_replaceable(out, "build")
    summary = _reusable(out, params)
    if summary is not None:
        logger.info("reusing build %s", out)
        return summary

    t0 = time.perf_counter()
    camera = PinholeCamera(size[0], size[1], float(np.deg2rad(fovy_deg)))
    label = scene_slug(source)
    logger.info("building %s (%dx%d, seed %d, %s) -> %s", label, size[0], size[1], seed, texture, out)
    scenes: dict[str, Scene] = {}
    poses: dict[str, np.ndarray] = {}
    areas: dict[str, float] = {}
    steps = [(kind, step) for kind in LAYOUTS for step in ("scene", "ground truth and trajectory")]
    with tqdm(total=len(steps), desc=f"{label}: scenes", unit="step", disable=not progress) as bar:
        for i, kind in enumerate(LAYOUTS):
            bar.set_description(f"{label}: {LAYOUTS[kind]} layout, scene")
            lighting = query_lighting if kind == "query" else "default"
            scenes[kind] = load_scene(source, layout=LAYOUTS[kind], texture=texture, lighting=lighting)
            bar.update()
            bar.set_description(f"{label}: {LAYOUTS[kind]} layout, ground truth and trajectory")
            gt = ground_truth_map(
                scenes[kind], resolution=GRID_RESOLUTION, robot_radius=ROBOT_RADIUS, robot_height=ROBOT_HEIGHT
            )
            areas[kind] = float(gt.navigable.sum()) * gt.spec.resolution**2
            rng = np.random.default_rng([seed, i])
            poses[kind] = coverage_trajectory(gt.navigable, gt.spec, rng, **TRAJECTORIES[kind])
            logger.info("%s trajectory: %d frames over %.1f m2", kind, len(poses[kind]), areas[kind])
            bar.update()

    name = scenes["database"].name
    runs: dict[str, tuple[Run, np.ndarray]] = {}
    total = sum(len(p) for p in poses.values())
    with tqdm(total=total, desc=f"{label}: rendering", unit="frame", disable=not progress) as bar:
        for kind, scene in scenes.items():
            images, depth = _render_run(scene, poses[kind], camera, bar)
            meta = {
                "scene": name,
                "source": str(source),
                "layout": scene.layout,
                "kind": kind,
                "seed": seed,
                "texture": scene.texture,
                "lighting": scene.lighting,
            }
            runs[kind] = (Run(images, poses[kind], camera, meta), depth)

    summary = {
        "format": BUILD_FORMAT,
        "version": BUILD_VERSION,
        "scene": name,
        "source": str(source),
        "database_frames": len(runs["database"][0]),
        "query_frames": len(runs["query"][0]),
        "navigable_area_m2": round(areas["database"], 3),
        "query_navigable_area_m2": round(areas["query"], 3),
        "width": size[0],
        "height": size[1],
        "seed": seed,
        "texture": scenes["database"].texture,
        "fovy_deg": float(fovy_deg),
        "query_lighting": query_lighting,
        "run_format_version": RUN_VERSION,
        "parameters": params,
    }

    def write(tmp: Path) -> None:
        with tqdm(total=total, desc=f"{label}: writing", unit="frame", disable=not progress) as bar:
            for kind, (run, depth) in runs.items():
                bar.set_description(f"{label}: writing the {kind} run")
                (tmp / kind).mkdir()
                write_run(tmp / kind, run, depth, on_frame=bar.update)
        summary["build_seconds"] = round(time.perf_counter() - t0, 2)
        write_json(tmp / "summary.json", summary)

    atomic_directory(out, write, "build")
    logger.info(
        "built %s: %d database + %d query frames in %.1f s -> %s",
        name,
        summary["database_frames"],
        summary["query_frames"],
        summary["build_seconds"],
        out,
    )
    return summary


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``vgpnav build``."""
    from vgpnav_env.scenes import BUILTIN_SCENES, TEXTURE_LEVELS
    from vgpnav_env.scenes.lighting import LIGHTING_LEVELS

    parser.add_argument(
        "scene",
        help=f"scene source: built-in ({', '.join(BUILTIN_SCENES)}), procedural 'style:seed' (e.g. home:7), "
        "a spec .yaml file or a mesh-scene directory",
    )
    parser.add_argument(
        "--out", type=Path, help="output directory (default: $VGPNAV_CACHE/<scene>-<W>x<H>-s<seed>-<texture>)"
    )
    parser.add_argument(
        "--size", type=size_arg, default=DEFAULT_SIZE, metavar="WxH", help="image size (default 320x240)"
    )
    parser.add_argument("--seed", type=seed_arg, default=0, help="trajectory seed, non-negative (default 0)")
    parser.add_argument(
        "--texture", choices=TEXTURE_LEVELS, default="realistic", help="texture level (default realistic)"
    )
    parser.add_argument(
        "--fovy",
        type=float,
        default=FOVY_DEG,
        help=f"vertical field of view in degrees (default {FOVY_DEG:g})",
    )
    parser.add_argument(
        "--query-lighting",
        choices=LIGHTING_LEVELS,
        default="default",
        help="lighting of the query run (default default)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    """``vgpnav build``: build (or reuse) the runs and write the summary as JSON to stdout."""
    summary = build_runs(
        args.scene,
        args.out,
        size=args.size,
        seed=args.seed,
        texture=args.texture,
        fovy_deg=args.fovy,
        query_lighting=args.query_lighting,
        progress=not args.quiet,
    )
    out = args.out or default_build_dir(args.scene, args.size, args.seed, args.texture)
    report = {k: v for k, v in summary.items() if k != "parameters"}
    sys.stdout.write(json.dumps({"path": str(out), **report}, indent=2) + "\n")
    return 0
