"""Shared test fixtures: a tiny textured room built directly as a ``Scene``.

``tiny_scene`` is a 4 m (x) by 5 m (y) room, floor at z = 0, walls 0.1 m thick and 2.5 m high
whose inner faces bound x in [0, 4] and y in [0, 5], plus two boxes (see ``TINY_BOXES``) and a
small red marker cube on top of box ``box_a``. Every mesh carries UVs in tiles (metres / tile_m)
and a noisy checker texture, so features and depth are well defined everywhere.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image
from trimesh.visual import TextureVisuals

from vgpnav_env.perception.database import Database, DatabaseConfig, open_database
from vgpnav_env.scenes.scene import Material, Scene, SceneMesh

ROOM_X = 4.0
ROOM_Y = 5.0
WALL_T = 0.1
WALL_H = 2.5
#: name -> (centre xyz, extents xyz) of the free-standing boxes in ``tiny_scene``.
TINY_BOXES = {
    "box_a": ((1.0, 1.5, 0.4), (0.6, 0.8, 0.8)),
    "box_b": ((3.0, 3.5, 0.25), (0.8, 0.5, 0.5)),
}
#: The marker cube sits centred on top of ``box_a``.
MARKER = ((1.0, 1.5, 0.85), (0.1, 0.1, 0.1))
#: Camera size (W, H) of ``home_build`` and of the envs that perceive against it: the smallest at
#: which the classical backbone localizes most of home's queries (measured on 20 queries: 160x120
#: 3 localized, 17 lost; 240x180 15 localized, 5 lost).
HOME_SIZE = (240, 180)
#: How the tests open the ``home_build`` database (fixture ``home_database``): no prior map (the
#: wrapper's behaviour does not depend on it and building it is slow) and no stored RootSIFT
#: features (the simulated backbone never reads them; the classical backbone extracts the
#: references it uses on first use).
HOME_DATABASE_CONFIG = DatabaseConfig(prior="none", store_features=False)


def checker_texture(seed: int, size: int = 128, cells: int = 8, base=(200, 180, 150)) -> np.ndarray:
    """uint8 (size, size, 3) checker with per-pixel noise (deterministic for a seed)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size] // (size // cells)
    check = ((yy + xx) % 2).astype(float)[..., None]
    img = np.asarray(base, float) * (0.55 + 0.45 * check) + rng.normal(0.0, 18.0, (size, size, 3))
    return np.clip(img, 0, 255).astype(np.uint8)


def textured_box(extents, centre, material: Material) -> trimesh.Trimesh:
    """Axis-aligned box in W with per-face UVs in tiles (face-planar coordinates / tile_m)."""
    box = trimesh.creation.box(extents=extents)
    box.apply_translation(centre)
    box = box.copy()
    box.unmerge_vertices()
    normals = np.repeat(box.face_normals, 3, axis=0)
    verts = box.vertices[box.faces.reshape(-1)]
    axis = np.abs(normals).argmax(axis=1)
    # In-plane axes per dominant normal: x-faces use (y, z), y-faces (x, z), z-faces (x, y).
    a = np.where(axis == 0, 1, 0)
    b = np.where(axis == 2, 1, 2)
    idx = np.arange(len(verts))
    uv = np.stack([verts[idx, a], verts[idx, b]], axis=1) / material.tile_m
    mesh = trimesh.Trimesh(vertices=verts, faces=np.arange(len(verts)).reshape(-1, 3), process=False)
    image = Image.fromarray(material.image) if material.image is not None else None
    mesh.visual = TextureVisuals(uv=uv, image=image)
    return mesh


def _part(name: str, category: str, extents, centre, material: Material, collide: bool = True) -> SceneMesh:
    mesh = textured_box(extents, centre, material)
    collision = [
        trimesh.creation.box(extents=extents, transform=trimesh.transformations.translation_matrix(centre))
    ]
    return SceneMesh(name, category, mesh, material, collision if collide else [])


def make_tiny_scene(
    with_boxes: bool = True,
    inner_wall: bool = False,
    materials: tuple[Material, Material, Material] | None = None,
    texture: str = "checker",
) -> Scene:
    """The tiny room; ``inner_wall`` adds a 0.1 m wall at y = 2.5 from x = 0 to 3 (gap at x > 3).

    ``materials`` = (floor, wall, box) replaces the default checker materials (``texture`` names them).
    """
    floor_mat, wall_mat, box_mat = materials or (
        Material("floor", (1.0, 1.0, 1.0, 1.0), checker_texture(0, base=(170, 120, 80)), tile_m=1.0),
        Material("wall", (1.0, 1.0, 1.0, 1.0), checker_texture(1, base=(220, 220, 210)), tile_m=1.5),
        Material("box", (1.0, 1.0, 1.0, 1.0), checker_texture(2, base=(60, 110, 200)), tile_m=0.5),
    )
    marker_mat = Material("marker", (1.0, 0.0, 0.0, 1.0))
    t, h = WALL_T, WALL_H
    meshes = [
        _part(
            "floor",
            "floor",
            (ROOM_X + 2 * t, ROOM_Y + 2 * t, 0.02),
            (ROOM_X / 2, ROOM_Y / 2, -0.01),
            floor_mat,
            False,
        ),
        _part("wall_south", "wall", (ROOM_X + 2 * t, t, h), (ROOM_X / 2, -t / 2, h / 2), wall_mat),
        _part("wall_north", "wall", (ROOM_X + 2 * t, t, h), (ROOM_X / 2, ROOM_Y + t / 2, h / 2), wall_mat),
        _part("wall_west", "wall", (t, ROOM_Y, h), (-t / 2, ROOM_Y / 2, h / 2), wall_mat),
        _part("wall_east", "wall", (t, ROOM_Y, h), (ROOM_X + t / 2, ROOM_Y / 2, h / 2), wall_mat),
    ]
    if inner_wall:
        meshes.append(_part("wall_inner", "wall", (3.0, t, h), (1.5, 2.5, h / 2), wall_mat))
    if with_boxes:
        for name, (centre, extents) in TINY_BOXES.items():
            meshes.append(_part(name, "box", extents, centre, box_mat))
        meshes.append(_part("marker", "marker", MARKER[1], MARKER[0], marker_mat, False))
    layout = "base" if with_boxes else "empty"
    if inner_wall:
        layout += "_wall"
    return Scene("tiny", layout, texture, meshes)


@pytest.fixture(scope="session")
def tiny_scene() -> Scene:
    return make_tiny_scene()


@pytest.fixture(scope="session")
def empty_room() -> Scene:
    return make_tiny_scene(with_boxes=False)


@pytest.fixture(scope="session")
def walled_room() -> Scene:
    return make_tiny_scene(with_boxes=False, inner_wall=True)


@pytest.fixture(scope="session")
def home_build(tmp_path_factory: pytest.TempPathFactory):
    """Directory of the built-in ``home`` scene's database + query runs (HOME_SIZE, seed 0,
    realistic), built once per test session; read it with ``vgpnav_env.runs.load_build``."""
    from vgpnav_env.build import build_runs

    out = tmp_path_factory.mktemp("builds") / "home-{}x{}-s0-realistic".format(*HOME_SIZE)
    build_runs("home", out, size=HOME_SIZE, seed=0, progress=False)
    return out


@pytest.fixture(scope="session")
def home_database(home_build):
    """The ``home_build`` database opened with :data:`HOME_DATABASE_CONFIG`, once per session:
    ``open_database`` returns this object to every later call with the same directory and
    settings (e.g. ``evaluate_navigation(database_dir=home_build, wrapper_kwargs=...)``)."""
    return open_database(home_build, HOME_DATABASE_CONFIG)


@pytest.fixture(scope="session")
def tiny_build_source(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``tiny_build.make_tiny_build`` rendered once per session, its database prepared as the
    protocols open it (index and stored features, no prior); tests use ``tiny_build_dir``."""
    from tiny_build import make_tiny_build

    out = make_tiny_build(tmp_path_factory.mktemp("tiny_source") / "build")
    Database.open(out, config=DatabaseConfig(prior="none"), progress=False)
    return out


@pytest.fixture(scope="module")
def tiny_build_dir(tiny_build_source: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A private copy (per test module) of the session's tiny build: modules write their own
    index caches into it."""
    return Path(shutil.copytree(tiny_build_source, tmp_path_factory.mktemp("tiny") / "build"))
