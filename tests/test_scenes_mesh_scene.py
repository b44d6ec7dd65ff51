"""Mesh-scene directories: export of built-in layouts and loading back (z-up, y-up + scale)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from vgpnav_env.geometry import PinholeCamera, camera_pose
from vgpnav_env.groundtruth import ground_truth_map
from vgpnav_env.render import MujocoRenderer
from vgpnav_env.scenes import Scene, SceneError, list_layouts, load_scene, scene_slug
from vgpnav_env.scenes.mesh_scene import export_mesh_scene, load_mesh_scene


def _assert_same(loaded: Scene, orig: Scene) -> None:
    assert sorted(m.name for m in loaded.meshes) == sorted(m.name for m in orig.meshes)
    by_name = {m.name: m for m in orig.meshes}
    for m in loaded.meshes:
        o = by_name[m.name]
        assert m.category == o.category
        np.testing.assert_allclose(m.mesh.vertices, o.mesh.vertices, atol=1e-5)
        np.testing.assert_allclose(m.mesh.bounds, o.mesh.bounds, atol=1e-5)
        np.testing.assert_allclose(m.mesh.visual.uv, o.mesh.visual.uv, atol=1e-5)
        np.testing.assert_array_equal(m.material.image, o.material.image)
        assert (m.collision == []) == (o.collision == [])
        for c in m.collision:
            assert c.is_convex
    np.testing.assert_allclose(loaded.bounds, orig.bounds, atol=1e-5)


@pytest.fixture(scope="module")
def home_exported(tmp_path_factory) -> tuple[Scene, Path]:
    """The built-in ``home`` and its export as a mesh-scene directory (read only, exported once)."""
    base = load_scene("home")
    return base, export_mesh_scene(base, tmp_path_factory.mktemp("export") / "flat")


def test_export_load_round_trip_z_up(home_exported) -> None:
    base, out = home_exported
    assert list_layouts(str(out)) == ["base"] and scene_slug(str(out)) == "flat"
    loaded = load_scene(str(out))
    assert loaded.layout == "base" and loaded.texture == "native"
    _assert_same(loaded, base)


@pytest.mark.slow
def test_round_trip_renders_like_the_original(home_exported) -> None:
    """Exported + reloaded home renders the same images (measured: RGB mean |diff| ~5e-5 grey
    levels, depth max |diff| ~1e-5 m); tolerances: depth 1 mm everywhere, RGB mean 0.5."""
    base, out = home_exported
    loaded = load_scene(str(out))
    camera = PinholeCamera(160, 120, np.deg2rad(60.0))
    gt = ground_truth_map(base)
    rng = np.random.default_rng(5)
    cells = np.argwhere(gt.navigable)
    poses = [
        camera_pose([*gt.spec.cell_to_world(cells[i]), 1.5], rng.uniform(-np.pi, np.pi), np.deg2rad(20.0))
        for i in rng.choice(len(cells), 6, replace=False)
    ]
    with MujocoRenderer(base, camera) as a, MujocoRenderer(loaded, camera) as b:
        for T_wc in poses:
            fa, fb = a.render(T_wc), b.render(T_wc)
            both = np.isfinite(fa.depth) & np.isfinite(fb.depth)
            assert np.array_equal(np.isfinite(fa.depth), np.isfinite(fb.depth))
            assert np.abs(fa.depth - fb.depth)[both].max() < 1e-3
            assert np.abs(fa.rgb.astype(float) - fb.rgb).mean() < 0.5


def _subset(scene: Scene, keep: set[str]) -> Scene:
    return Scene("small", scene.layout, scene.texture, [m for m in scene.meshes if m.name in keep])


def test_export_load_round_trip_y_up_with_scale_and_layouts(tmp_path) -> None:
    keep = {
        "floor/living",
        "ceiling/living",
        "wall/south",
        "wall/corridor_south",
        "coffee_table",
        "coffee_table/legs",
        "picture_sofa",
        "picture_sofa/canvas",
        "shelf_living/books",
        "plant_living",
        "person_living",
    }
    base, changed = _subset(load_scene("home"), keep), _subset(load_scene("home", "changed"), keep)
    out = export_mesh_scene([base, changed], tmp_path / "small", up="y", scale=0.01)
    data = json.loads((out / "layout.json").read_text())
    assert data["up"] == "y" and data["scale"] == 0.01
    raw = trimesh.load(out / data["objects"][0]["mesh"], force="mesh")
    assert raw.extents.max() > 20  # stored in centimetres, y up
    assert list_layouts(str(out)) == ["base", "changed"]
    _assert_same(load_mesh_scene(out), base)
    _assert_same(load_mesh_scene(out, layout="changed"), changed)


def test_foreign_structure_is_classified_and_gets_convex_collision(tmp_path) -> None:
    """A single untagged structure mesh (floor slab, a thick wall, a zero-thickness wall with a door
    gap) and an object with an euler rotation in its bbox, y up, in millimetres."""
    floor = trimesh.creation.box(extents=(4, 3, 0.02))
    floor.apply_translation((2, 1.5, -0.01))
    wall = trimesh.creation.box(extents=(4, 0.1, 2.5))
    wall.apply_translation((2, 0.0, 1.25))
    # A zero-thickness wall at x = 4 from y 0..3 with a door gap y in [1, 2] below z = 2.
    v = np.array(
        [
            [4, 0, 0],
            [4, 1, 0],
            [4, 1, 2.5],
            [4, 0, 2.5],
            [4, 2, 0],
            [4, 3, 0],
            [4, 3, 2.5],
            [4, 2, 2.5],
            [4, 1, 2],
            [4, 2, 2],
        ],
        float,
    )
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7], [8, 9, 7], [8, 7, 2]])
    thin = trimesh.Trimesh(v, f, process=False)
    z_to_y = (
        np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]], float)
        * np.array([1000, 1000, 1000, 1])[:, None]
    )
    structure = trimesh.util.concatenate([floor, wall, thin]).apply_transform(z_to_y)
    (tmp_path / "objects").mkdir()
    structure.export(tmp_path / "structure.ply")
    trimesh.creation.box(extents=(2, 2, 2)).export(tmp_path / "objects" / "crate.obj")
    layout = {
        "structure": "structure.ply",
        "up": "y",
        "scale": 0.001,
        "objects": [
            {
                "name": "crate",
                "category": "box",
                "mesh": "objects/crate.obj",
                "bbox": {"centre": [2000, 300, -1500], "size": [600, 600, 400], "euler": [0, np.pi / 4, 0]},
            }
        ],
    }
    (tmp_path / "layout.json").write_text(json.dumps(layout))
    scene = load_mesh_scene(tmp_path)
    cats = [m.category for m in scene.meshes]
    assert cats.count("floor") == 1 and cats.count("box") == 1 and set(cats) == {"floor", "wall", "box"}
    floor_m = next(m for m in scene.meshes if m.category == "floor")
    assert floor_m.collision == [] and floor_m.mesh.bounds[1, 2] == pytest.approx(0.0, abs=1e-9)
    thin = [
        c for m in scene.meshes if m.category == "wall" and m.mesh.bounds[0, 0] > 3.9 for c in m.collision
    ]
    assert thin and all(c.is_convex for c in thin)
    # the door gap (y in [1, 2], z < 2) stays open; the solid parts beside it are covered
    assert not any(c.bounds[0, 1] < 1.5 < c.bounds[1, 1] and c.bounds[0, 2] < 1.0 for c in thin)
    for y in (0.5, 2.5):
        assert any(
            c.bounds[0, 1] < y < c.bounds[1, 1] and c.bounds[0, 2] < 1.0 < c.bounds[1, 2] for c in thin
        )
    crate = scene.mesh("crate")
    # file size (x 0.6, y-up 0.6, z 0.4) turned 45 deg about file y (= W z): footprint (0.6 + 0.4) / sqrt 2
    np.testing.assert_allclose(crate.mesh.extents, (1 / np.sqrt(2), 1 / np.sqrt(2), 0.6), atol=1e-6)
    np.testing.assert_allclose(crate.mesh.bounds.mean(axis=0), (2.0, 1.5, 0.3), atol=1e-6)
    assert len(crate.collision) == 1 and crate.collision[0].is_convex


def test_bad_mesh_scene_directories(tmp_path) -> None:
    with pytest.raises(SceneError, match="no layout.json"):
        load_scene(str(tmp_path))
    (tmp_path / "layout.json").write_text(json.dumps({"objects": []}))
    with pytest.raises(SceneError, match="missing 'structure'"):
        load_mesh_scene(tmp_path)
    (tmp_path / "layout.json").write_text(json.dumps({"structure": "nope.glb", "up": "x"}))
    with pytest.raises(SceneError, match=r"up axis 'x' not allowed; allowed: \['z', 'y'\]"):
        load_mesh_scene(tmp_path)
    with pytest.raises(SceneError, match="does not exist"):
        load_mesh_scene(tmp_path, up="z")
