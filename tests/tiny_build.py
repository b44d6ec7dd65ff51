"""A small rendered build (database + query runs) of a textured 4 m x 5 m room with two boxes.

The room is ``tests/conftest.py``'s tiny room, but every texture spans a whole 4 m tile
(512 px multi-scale blob noise), so it does not repeat across the views: periodic textures alias
wide-baseline two-view geometry (a 1.2 m shift over a 1.5 m texture period looks like a
0.3 m shift the other way), which is a property of that texture, not of the pipeline.

Database: 1.5 m cameras on a 3 x 4 grid of positions, 4 headings each (pitch 25 deg down);
query: 1.2 m cameras (pitch 20 deg down) between those positions, headings off-grid by 20 deg.
Written in the on-disk build format (``summary.json``, ``database/``, ``query/`` with depth), so
``vgpnav_env.runs.load_build`` and the ``--build DIR`` option of the eval protocols read it.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from conftest import make_tiny_scene

from vgpnav_env.geometry import PinholeCamera, camera_pose
from vgpnav_env.render import MujocoRenderer
from vgpnav_env.runs import BUILD_FORMAT, BUILD_VERSION, Run, save_run, write_json
from vgpnav_env.scenes.scene import Material, Scene

QUERY_HEIGHT = 1.2


def blob_texture(seed: int, base, size: int = 512) -> np.ndarray:
    """uint8 (size, size, 3) multi-scale blob noise around colour ``base`` (no periodic pattern)."""
    rng = np.random.default_rng(seed)
    tex = np.zeros((size, size), np.float32)
    for sigma in (1.0, 2.5, 6.0):
        layer = cv2.GaussianBlur(rng.standard_normal((size, size)).astype(np.float32), (0, 0), sigma)
        tex += layer / layer.std()
    tex = (tex - tex.mean()) / tex.std()
    img = np.asarray(base, np.float32) * (1.0 + 0.35 * tex[..., None])
    return np.clip(img, 0, 255).astype(np.uint8)


def textured_room() -> Scene:
    """The tiny room (walls, two boxes, marker) with non-repeating 4 m textures."""

    def material(name: str, seed: int, base) -> Material:
        return Material(name, (1.0, 1.0, 1.0, 1.0), blob_texture(seed, base), tile_m=4.0)

    materials = (
        material("floor", 0, (170, 120, 80)),
        material("wall", 1, (220, 220, 210)),
        material("box", 2, (60, 110, 200)),
    )
    return make_tiny_scene(materials=materials, texture="blob")


def _poses() -> dict[str, list[np.ndarray]]:
    db = [
        camera_pose([x, y, 1.5], yaw, np.deg2rad(25.0))
        for x in (0.8, 2.0, 3.2)
        for y in (0.8, 2.0, 3.0, 4.2)
        for yaw in np.deg2rad([0.0, 90.0, 180.0, 270.0])
    ]
    query = [
        camera_pose([x, y, QUERY_HEIGHT], yaw, np.deg2rad(20.0))
        for x, y, yaw in [
            (1.4, 2.6, 20.0),
            (2.6, 2.5, 110.0),
            (2.5, 1.3, 200.0),
            (1.5, 3.6, 290.0),
            (2.7, 3.0, 70.0),
            (1.3, 1.0, 160.0),
        ]
        for yaw in [np.deg2rad(yaw)]
    ]
    return {"database": db, "query": query}


def make_tiny_build(out: Path, size: tuple[int, int] = (160, 120)) -> Path:
    """Render and save the tiny build (database and query in the same layout) into ``out``."""
    scene = textured_room()
    camera = PinholeCamera(size[0], size[1], np.deg2rad(60.0))
    out.mkdir(parents=True, exist_ok=True)
    counts = {}
    with MujocoRenderer(scene, camera) as renderer:
        for kind, poses in _poses().items():
            frames = [renderer.render(T) for T in poses]
            meta = {
                "scene": "tiny",
                "layout": scene.layout,
                "kind": kind,
                "seed": 0,
                "texture": scene.texture,
                "lighting": "default",
            }
            run = Run(np.stack([f.rgb for f in frames]), np.stack(poses), camera, meta)
            save_run(out / kind, run, np.stack([f.depth for f in frames]))
            counts[kind] = len(poses)
    write_json(
        out / "summary.json",
        {
            "format": BUILD_FORMAT,
            "version": BUILD_VERSION,
            "scene": "tiny",
            "database_frames": counts["database"],
            "query_frames": counts["query"],
            "width": size[0],
            "height": size[1],
        },
    )
    return out
