"""Scene specs, built-in scenes, procedural scenes and the load_scene entry point."""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict

import numpy as np
import pytest
import trimesh
import yaml

from vgpnav_env.scenes import (
    BUILTIN_SCENES,
    LIGHTING_LEVELS,
    TEXTURE_LEVELS,
    SceneError,
    build_scene,
    list_layouts,
    load_scene,
    load_scene_spec,
    object_of,
    parse_spec,
    scene_slug,
)
from vgpnav_env.scenes.freespace import connectivity_report
from vgpnav_env.scenes.materials import parse_material_name
from vgpnav_env.scenes.primitives import PRIMITIVES
from vgpnav_env.scenes.procedural import generate, load_catalogue
from vgpnav_env.scenes.spec import load_spec

MINIMAL = {
    "name": "mini",
    "rooms": [
        {"name": "a", "rect": [0, 0, 4, 3]},
        {"name": "b", "rect": [4, 0, 7, 3], "floor": "tiles:white"},
    ],
    "walls": [
        {"from": [0, 0], "to": [7, 0]},
        {"from": [4, 0], "to": [4, 3], "doors": [{"at": 1.5, "width": 1.0}]},
    ],
    "objects": [
        {"name": "t", "kind": "table", "pose": [2, 1.5, 90]},
        {"name": "s", "kind": "sofa", "pose": [5.5, 0.5, 0], "material": "fabric:blue"},
    ],
    "layouts": {
        "changed": {
            "remove": ["s"],
            "move": {"t": [1.5, 1.0, 0]},
            "add": [{"name": "p", "kind": "person", "pose": [6, 2]}],
        }
    },
}


def _with(path: str, value: object) -> dict:
    """A deep copy of MINIMAL with one field (dotted path, list indices as ints) replaced."""
    d = yaml.safe_load(yaml.safe_dump(MINIMAL))
    keys = [int(k) if k.isdigit() else k for k in path.split(".")]
    target = d
    for k in keys[:-1]:
        target = target[k]
    target[keys[-1]] = value
    return d


def test_parse_minimal_spec_and_layout_edits() -> None:
    spec = parse_spec(MINIMAL, source="mini.yaml")
    assert spec.layout_names == ["base", "changed"]
    assert spec.floor_area == pytest.approx(21.0)
    t = {o.name: o for o in spec.objects}["t"]
    assert t.yaw == pytest.approx(math.pi / 2) and t.category == "table"
    changed = {o.name: o for o in spec.layout_objects("changed")}
    assert set(changed) == {"t", "p"}
    assert (changed["t"].x, changed["t"].y, changed["t"].yaw) == pytest.approx((1.5, 1.0, 0.0))
    assert changed["p"].kind == "person"


@pytest.mark.parametrize(
    ("path", "value", "needle"),
    [
        ("rooms.0.rect", [0, 0, -1, 3], "rooms[0].rect"),
        ("rooms.0.floor", "velvet", "unknown material kind 'velvet'"),
        ("rooms.1.floor", "tiles:purple", "variants"),
        ("walls.1.doors.0.at", 2.9, "does not fit"),
        ("objects.0.kind", "spaceship", "objects[0].kind"),
        ("objects.1.pose", [1], "objects[1].pose"),
        ("objects.0.colour", "red", "unknown key(s) ['colour']"),
        ("layouts.changed.move", {"ghost": [0, 0, 0]}, "no base object named 'ghost'"),
        ("layouts.base", {}, "'base' is the unedited layout"),
        ("rooms", [], "at least one room"),
    ],
)
def test_malformed_spec_names_file_field_and_problem(path: str, value: object, needle: str) -> None:
    with pytest.raises(SceneError) as err:
        parse_spec(_with(path, value), source="bad.yaml")
    msg = str(err.value)
    assert msg.startswith("bad.yaml: ") and needle in msg, msg
    assert isinstance(err.value, ValueError)


def test_bad_yaml_file_names_the_file(tmp_path) -> None:
    f = tmp_path / "broken.yaml"
    f.write_text("name: [unclosed\n")
    with pytest.raises(SceneError, match="broken.yaml: invalid YAML"):
        load_spec(f)
    with pytest.raises(SceneError, match="unknown kind"):
        f.write_text(yaml.safe_dump(_with("objects.0.kind", "nope")))
        load_scene(str(f))


def test_unknown_source_layout_texture_list_allowed_values() -> None:
    with pytest.raises(SceneError, match=r"allowed: \['base', 'changed', 'changed2'\]"):
        load_scene("home", layout="moved")
    with pytest.raises(SceneError, match=r"allowed: \['rich', 'realistic', 'sparse'\]"):
        load_scene("home", texture="glossy")
    with pytest.raises(SceneError, match="lighting"):
        load_scene("home", lighting="disco")
    with pytest.raises(SceneError, match=r"built-in name \['home', 'hospital'\]"):
        load_scene("castle")
    with pytest.raises(SceneError, match="procedural style 'castle'"):
        load_scene("castle:3")


def test_slugs_and_layout_lists(tmp_path) -> None:
    assert scene_slug("home") == "home" and scene_slug("hospital:12") == "hospital-12"
    f = tmp_path / "my flat.yaml"
    f.write_text(yaml.safe_dump(MINIMAL))
    assert scene_slug(str(f)) == "my_flat"
    assert list_layouts(str(f)) == ["base", "changed"]
    assert list_layouts("home")[:2] == ["base", "changed"]
    assert set(TEXTURE_LEVELS) == {"rich", "realistic", "sparse"} and "default" in LIGHTING_LEVELS


@pytest.fixture(scope="module")
def home():
    return load_scene("home")


@pytest.fixture(scope="module")
def home_changed():
    return load_scene("home", "changed")


def _floor_area(scene) -> float:
    area = 0.0
    for m in scene.meshes:
        if m.category == "floor":
            up = m.mesh.face_normals[:, 2] > 0.9
            area += float(m.mesh.area_faces[up].sum())
    return area


@pytest.mark.parametrize(("name", "lo", "hi"), [("home", 80, 120), ("hospital", 150, 250)])
def test_builtin_floor_area_doors_and_connectivity(name: str, lo: float, hi: float) -> None:
    spec = load_scene_spec(name)
    assert lo <= spec.floor_area <= hi
    assert lo <= _floor_area(load_scene(name)) <= hi
    assert "changed" in spec.layout_names
    doors = [(w, d) for w in spec.walls for d in w.doors]
    assert all(d.width >= 0.9 for _, d in doors)
    for room in spec.rooms:  # every room has a door on its boundary
        poly = np.asarray(room.polygon)
        touching = 0
        for w, d in doors:
            t = (np.asarray(w.end) - w.start) / w.length
            c = np.asarray(w.start) + d.at * t
            edges = zip(poly, np.roll(poly, -1, axis=0), strict=True)
            cross = [(b - a)[0] * (c - a)[1] - (b - a)[1] * (c - a)[0] for a, b in edges]
            touching += any(abs(x) < 1e-6 for x in cross)
        assert touching >= 1, f"room {room.name} has no door"
    for layout in spec.layout_names:
        lost_rooms, lost = connectivity_report(spec, spec.layout_objects(layout), robot_radius=0.2)
        assert lost_rooms == [], (layout, lost_rooms)
        assert lost < 0.1, (layout, lost)


def test_builtin_changed_has_people_and_edits() -> None:
    for name in BUILTIN_SCENES:
        spec = load_scene_spec(name)
        e = spec.edit("changed")
        assert len(e.move) >= 3 and len(e.remove) >= 2
        assert sum(o.kind == "person" for o in e.add) >= 2


def test_mesh_names_categories_and_collision(home) -> None:
    names = [m.name for m in home.meshes]
    assert len(names) == len(set(names))
    cats = {m.category for m in home.meshes}
    assert {"floor", "wall", "ceiling", "sofa", "bed", "table", "chair", "shelf"} <= cats
    for m in home.meshes:
        assert isinstance(m.mesh.visual, trimesh.visual.TextureVisuals) and m.material.image is not None
        if m.category in ("floor", "ceiling", "trim", "picture", "poster", "rug", "panel"):
            assert m.collision == []
        for c in m.collision:
            assert c.is_convex and c.volume > 0
    assert all(home.mesh(f"wall/{w}").collision for w in ("south", "corridor_south"))
    lo, hi = home.bounds
    assert lo[2] == pytest.approx(-0.02) and hi[2] == pytest.approx(2.62)
    assert object_of("sofa/cushion") == "sofa" and object_of("wall/south") == "wall/south"


def test_uv_scale_is_metric_on_every_face(home) -> None:
    for m in home.meshes:
        tri = m.mesh.vertices[m.mesh.faces]
        uv = m.mesh.visual.uv[m.mesh.faces]
        metric = np.linalg.norm(tri[:, [1, 2, 0]] - tri, axis=-1)
        tex = np.linalg.norm(uv[:, [1, 2, 0]] - uv, axis=-1)
        ok = metric > 1e-4
        ratio = tex[ok] / metric[ok] * m.material.tile_m
        assert np.all(np.abs(ratio - 1) < 0.1), (m.name, ratio.min(), ratio.max())


def test_changed_differs_from_base_exactly_in_edited_objects(home, home_changed) -> None:
    spec = load_scene_spec("home")
    edit = spec.edit("changed")
    base = {m.name: m for m in home.meshes}
    changed = {m.name: m for m in home_changed.meshes}
    differs = set()
    for n in set(base) | set(changed):
        if n not in base or n not in changed:
            differs.add(object_of(n))
        elif not np.array_equal(base[n].mesh.vertices, changed[n].mesh.vertices):
            differs.add(object_of(n))
        else:
            assert base[n].material is changed[n].material
    assert differs == edit.edited_names


def test_same_arguments_same_scene_and_cache(home) -> None:
    assert load_scene("home") is home
    rebuilt = build_scene(load_scene_spec("home"))
    for a, b in zip(home.meshes, rebuilt.meshes, strict=True):
        assert a.name == b.name
        np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
        np.testing.assert_array_equal(a.material.image, b.material.image)


#: Digests of ``generate(style, 3)``, measured when the catalogue moved from Python literals to
#: ``builtin/catalogue.yaml`` (seeds 0-5 of both styles gave identical specs before and after).
PROCEDURAL_DIGESTS = {"home": "4eb57ae89f93f6bf", "hospital": "6405836c2596e7be"}


def test_procedural_catalogue_is_valid_package_data() -> None:
    catalogue = load_catalogue()
    assert set(catalogue.furniture) == set(catalogue.floors) == set(catalogue.paints) == {"home", "hospital"}
    materials = [m for style in catalogue.paints.values() for m in style]
    materials += [m for rooms in catalogue.floors.values() for room in rooms.values() for m in room]
    materials += [*catalogue.tops, *catalogue.trousers, *catalogue.skins]
    for style, rooms in catalogue.furniture.items():
        assert set(rooms) == set(catalogue.floors[style])  # every room kind has furniture and floors
        for item in (item for items in rooms.values() for item in items):
            assert item.kind in PRIMITIVES and item.place in ("wall", "free", "table")
            assert all(lo <= hi for lo, hi in item.size) and 0 <= item.count[0] <= item.count[1]
            materials += [*item.materials, *(m for _, choices in item.roles for m in choices)]
    for name in materials:
        parse_material_name(name)  # raises on an unknown material
    assert catalogue.movable <= set(PRIMITIVES)


@pytest.mark.parametrize(("style", "lo", "hi"), [("home", 80, 120), ("hospital", 150, 250)])
def test_procedural_scenes(style: str, lo: float, hi: float) -> None:
    a, b, c = generate(style, 3), generate(style, 3), generate(style, 4)
    assert a == b
    digest = hashlib.sha256(json.dumps(asdict(a), sort_keys=True, default=repr).encode()).hexdigest()
    assert digest[:16] == PROCEDURAL_DIGESTS[style]
    assert a.objects != c.objects and a.rooms != c.rooms
    for spec in (a, c):
        assert lo <= spec.floor_area <= hi
        assert {r.kind for r in spec.rooms} >= (
            {"living", "kitchen", "bedroom", "bath", "corridor"}
            if style == "home"
            else {"ward", "reception", "corridor"}
        )
        for layout in spec.layout_names:
            lost_rooms, lost = connectivity_report(spec, spec.layout_objects(layout), robot_radius=0.2)
            assert lost_rooms == [] and lost < 0.1, (spec.name, layout, lost_rooms, lost)
        e = spec.edit("changed")
        assert e.move and e.remove and any(o.kind == "person" for o in e.add)
        for layout in spec.layout_names:
            names = [o.name for o in spec.layout_objects(layout)]
            assert len(names) == len(set(names))
    sa = load_scene(f"{style}:3")
    assert sa.name == f"{style}-3" and scene_slug(f"{style}:3") == f"{style}-3"
    rebuilt = build_scene(generate(style, 3))
    for x, y in zip(sa.meshes, rebuilt.meshes, strict=True):
        np.testing.assert_array_equal(x.mesh.vertices, y.mesh.vertices)
        np.testing.assert_array_equal(x.material.image, y.material.image)


def test_mesh_file_object_in_spec_is_fitted_into_its_size(tmp_path) -> None:
    trimesh.creation.icosphere(subdivisions=2, radius=3.0).export(tmp_path / "blob.ply")
    d = _with(
        "objects.1",
        {
            "name": "blob",
            "mesh": "blob.ply",
            "pose": [5.5, 1.5, 30],
            "size": [0.6, 0.4, 0.9],
            "category": "sculpture",
        },
    )
    del d["layouts"]
    f = tmp_path / "scene.yaml"
    f.write_text(yaml.safe_dump(d))
    scene = load_scene(str(f), texture="sparse")
    blob = scene.mesh("blob")
    assert blob.category == "sculpture" and len(blob.collision) == 1 and blob.collision[0].is_convex
    lo, hi = blob.mesh.bounds
    assert lo[2] == pytest.approx(0.0, abs=1e-9) and hi[2] == pytest.approx(0.9)
    assert (lo[:2] + hi[:2]) / 2 == pytest.approx((5.5, 1.5), abs=0.02)
    assert blob.mesh.visual.uv.shape == (len(blob.mesh.vertices), 2)
