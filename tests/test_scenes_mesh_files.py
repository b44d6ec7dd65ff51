"""Mesh files made by other people: asset paths, opacity, several materials, degenerate parts,
the load report, and the build cache keyed on every file a mesh-scene directory uses."""

from __future__ import annotations

import json
import logging

import mujoco
import numpy as np
import pytest
import trimesh
from conftest import make_tiny_scene
from PIL import Image

from vgpnav_env.build import build_runs
from vgpnav_env.scenes import Scene, SceneMesh, load_scene
from vgpnav_env.scenes.collision import THIN_BOX_M, part_collision
from vgpnav_env.scenes.mesh_files import resolve_asset
from vgpnav_env.scenes.mesh_scene import export_mesh_scene, load_mesh_scene, mesh_scene_digest
from vgpnav_env.scenes.model import build_model
from vgpnav_env.scenes.scene import Material

LAMP_MTL = """newmtl Shade
Kd 0.5 0.5 0.5
map_Kd C:\\Users\\someone\\Textures\\SHADE.PNG
newmtl Glass
Kd 0.2 0.3 0.4
d 0.25
newmtl Frosted
Kd 0.9 0.9 0.9
Tr 0.6
newmtl Lost
Kd 0.7 0.1 0.1
map_Kd -s 1 1 1 /home/author/wood/missing_wood.jpg
"""


def _box_lines(lo, hi, offset: int) -> tuple[list[str], list[str]]:
    """OBJ v and f lines of an axis-aligned box (faces outward), vertex indices from ``offset``."""
    v = [f"v {x} {y} {z}" for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    box = trimesh.creation.box(bounds=[lo, hi])
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    remap = [int(np.argmin(np.linalg.norm(corners - p, axis=1))) for p in box.vertices]
    f = [f"f {remap[a] + offset} {remap[b] + offset} {remap[c] + offset}" for a, b, c in box.faces]
    return v, f


def _write_lamp(folder, shade_rgb=(200, 40, 40)) -> None:
    """A 4-material OBJ (z up, metres): textured shade (Windows path, other case), glass (d),
    frosted (Tr) and a part whose texture is missing."""
    folder.mkdir(parents=True, exist_ok=True)
    img = np.zeros((8, 8, 3), np.uint8)
    img[...] = shade_rgb
    img[::2, ::2] = 255
    Image.fromarray(img).save(folder / "shade.png")
    (folder / "lamp.mtl").write_text(LAMP_MTL)
    lines = ["mtllib lamp.mtl"]
    n = 0
    for mat, lo, hi in (
        ("Shade", (-0.2, -0.2, 0.8), (0.2, 0.2, 1.2)),
        ("Glass", (-0.25, -0.25, 0.0), (0.25, 0.25, 0.1)),
        ("Frosted", (-0.05, -0.05, 0.1), (0.05, 0.05, 0.8)),
        ("Lost", (0.3, 0.3, 0.0), (0.4, 0.4, 0.1)),
    ):
        v, f = _box_lines(lo, hi, n + 1)
        if mat == "Shade":
            lines += v + [f"vt {i % 2} {i // 4}" for i in range(8)] + ["usemtl Shade"]
            lines += [" ".join(["f"] + [f"{k}/{k}" for k in line.split()[1:]]) for line in f]
        else:
            lines += v + [f"usemtl {mat}"] + f
        n += 8
    (folder / "lamp.obj").write_text("\n".join(lines) + "\n")


def test_resolve_asset_finds_what_authors_name(tmp_path) -> None:
    (tmp_path / "Textures").mkdir()
    (tmp_path / "Textures" / "Oak.JPG").write_bytes(b"x")
    (tmp_path / "beside.png").write_bytes(b"y")
    elsewhere = tmp_path / "other" / "abs.png"
    elsewhere.parent.mkdir()
    elsewhere.write_bytes(b"z")
    oak = tmp_path / "Textures" / "Oak.JPG"
    assert resolve_asset("Textures/Oak.JPG", tmp_path) == oak  # relative
    assert resolve_asset("textures\\oak.jpg", tmp_path) == oak  # backslashes, other case
    assert resolve_asset("C:\\Users\\me\\Desktop\\OAK.jpg", tmp_path) == oak  # Windows path: name below
    assert resolve_asset("/home/me/pics/beside.png", tmp_path) == tmp_path / "beside.png"  # name beside
    assert resolve_asset("-s 1 1 1 -o 0.5 0.5 beside.png", tmp_path) == tmp_path / "beside.png"  # options
    assert resolve_asset(str(elsewhere), tmp_path / "Textures") == elsewhere  # absolute, exists here
    assert resolve_asset("Plain001.jpg\t\t", tmp_path) is None  # missing (trailing tabs ignored)


def test_obj_materials_paths_opacity_and_missing_texture(tmp_path, caplog) -> None:
    _write_lamp(tmp_path / "objects" / "lamp")
    floor = trimesh.creation.box(bounds=[(-2, -2, -0.02), (2, 2, 0.0)])
    floor.export(tmp_path / "floor.ply")
    layout = {
        "structure": "floor.ply",
        "objects": [
            {
                "name": "lamp",
                "category": "lamp",
                "mesh": "objects/lamp/lamp.obj",
                "bbox": {"centre": [0.5, 0.5, 0.6], "size": [0.7, 0.7, 1.2]},
            }
        ],
    }
    (tmp_path / "layout.json").write_text(json.dumps(layout))
    with caplog.at_level(logging.WARNING, logger="vgpnav_env.scenes.mesh_scene"):
        scene, report = load_mesh_scene(tmp_path, report=True)
    parts = {m.name: m for m in scene.meshes if m.category == "lamp"}
    assert set(parts) == {"lamp", "lamp/Glass", "lamp/Frosted", "lamp/Lost"}  # one mesh per material
    shade = parts["lamp"].material
    np.testing.assert_array_equal(shade.image, np.asarray(Image.open(tmp_path / "objects/lamp/shade.png")))
    assert shade.rgba == (1.0, 1.0, 1.0, 1.0)  # a textured MTL material shows its image as is
    assert parts["lamp/Glass"].material.rgba == pytest.approx((0.2, 0.3, 0.4, 0.25), abs=2e-3)
    assert parts["lamp/Frosted"].material.rgba[3] == pytest.approx(0.4)  # Tr 0.6
    assert parts["lamp/Lost"].material.image is None
    assert parts["lamp/Lost"].material.rgba == pytest.approx((0.7, 0.1, 0.1, 1.0), abs=2e-3)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "missing_wood.jpg" in warnings[0]  # one warning naming the file
    assert len(report.missing) == 1 and "missing_wood.jpg" in report.missing[0]
    model = build_model(scene)
    alphas = sorted(np.round(model.mat_rgba[:, 3], 3))
    assert 0.25 in alphas and 0.4 in alphas  # opacity reaches the MuJoCo materials
    assert model.ntex == 1


def test_spec_mesh_object_keeps_each_material(tmp_path) -> None:
    _write_lamp(tmp_path / "lamp")
    spec = {
        "name": "lamp_room",
        "rooms": [{"name": "r", "rect": [0, 0, 3, 3]}],
        "walls": [{"from": [0, 0], "to": [3, 0]}],
        "objects": [
            {"name": "lamp", "mesh": "lamp/lamp.obj", "pose": [1.5, 1.5, 0], "size": [0.7, 0.7, 1.2]}
        ],
    }
    (tmp_path / "room.yaml").write_text(json.dumps(spec))
    scene = load_scene(str(tmp_path / "room.yaml"))
    lamp = [m for m in scene.meshes if m.name.split("/")[0] == "lamp"]
    assert [m.name for m in lamp] == ["lamp", "lamp/Glass", "lamp/Frosted", "lamp/Lost"]
    assert lamp[0].material.image is not None and lamp[1].material.image is not None  # fallback texture
    np.testing.assert_allclose(np.min([m.mesh.bounds[0] for m in lamp], axis=0), (1.15, 1.15, 0.0), atol=1e-9)
    assert len(lamp[0].collision) == 1 and lamp[0].collision[0].is_volume


def _degenerate_obj(path) -> None:
    """One object, one material group per kind of part: solid, flat screen, flat disc, a 1 mm wire,
    a 4 mm speck, a zero-area sliver and a single triangle."""
    groups: dict[str, tuple[list, list]] = {}
    box = trimesh.creation.box(bounds=[(0, 0, 0), (0.4, 0.4, 0.4)])
    groups["body"] = (box.vertices.tolist(), box.faces.tolist())
    groups["screen"] = (
        [[0.41, 0.05, 0.1], [0.41, 0.35, 0.1], [0.41, 0.35, 0.3], [0.41, 0.05, 0.3]],
        [[0, 1, 2], [0, 2, 3]],
    )
    ang = np.linspace(0, 2 * np.pi, 13)[:-1]
    disc = [[0.2, 0.2, 0.4]] + [[0.2 + 0.1 * np.cos(a), 0.2 + 0.1 * np.sin(a), 0.4] for a in ang]
    groups["soil"] = (disc, [[0, 1 + i, 1 + (i + 1) % 12] for i in range(12)])
    groups["wire"] = (
        [[0, 0.5, 0], [0, 0.5, 0.8], [0.001, 0.5, 0.8], [0.001, 0.5, 0]],
        [[0, 1, 2], [0, 2, 3]],
    )
    speck = trimesh.creation.box(bounds=[(0.1, 0.1, 0.45), (0.104, 0.104, 0.454)])
    groups["speck"] = (speck.vertices.tolist(), speck.faces.tolist())
    groups["sliver"] = ([[0, 0, 0], [0.1, 0, 0], [0.2, 0, 0]], [[0, 1, 2]])
    groups["tri"] = ([[0, -0.1, 0], [0.3, -0.1, 0], [0.3, -0.1, 0.3]], [[0, 1, 2]])
    lines, n = [f"mtllib {path.stem}.mtl"], 0
    for name, (v, f) in groups.items():
        lines += [f"v {x} {y} {z}" for x, y, z in v] + [f"usemtl {name}"]
        lines += [f"f {a + n + 1} {b + n + 1} {c + n + 1}" for a, b, c in f]
        n += len(v)
    path.write_text("\n".join(lines) + "\n")
    colours = {k: f"Kd {0.1 + 0.1 * i:.1f} 0.5 0.5" for i, k in enumerate(groups)}
    path.with_suffix(".mtl").write_text("".join(f"newmtl {k}\n{c}\n" for k, c in colours.items()))


def test_degenerate_parts_of_each_kind_get_valid_collision_and_compile(tmp_path) -> None:
    _degenerate_obj(tmp_path / "gadget.obj")
    # Structure: a floor quad and a single-sided wall quad (open surfaces, in centimetres, y up).
    (tmp_path / "structure.obj").write_text(
        "v 0 0 0\nv 300 0 0\nv 300 0 -300\nv 0 0 -300\n"
        "v 0 0 -300\nv 300 0 -300\nv 300 250 -300\nv 0 250 -300\n"
        "usemtl floor\nf 1 2 3\nf 1 3 4\nusemtl wall\nf 5 6 7\nf 5 7 8\n"
    )
    layout = {
        "structure": "structure.obj",
        "up": "y",
        "scale": 0.01,
        "objects": [
            {
                "name": "gadget",
                "mesh": "gadget.obj",
                "bbox": {"centre": [150, 40, -150], "size": [41, 80, 70]},
            }
        ],
    }
    (tmp_path / "layout.json").write_text(json.dumps(layout))
    scene, report = load_mesh_scene(tmp_path, report=True)
    text = "\n".join(report.fixes)
    for line in (
        "gadget/screen: flat part -> thin box",
        "gadget/soil: flat part -> thin box",
        "gadget/tri: flat part -> thin box",
        "gadget/wire: degenerate part (line) -> covered by the object's hull",
        "gadget/speck: tiny part",
        "sliver: no surface area -> dropped",
        "wall wall/",
    ):
        assert line in text, line
    names = {m.name: m for m in scene.meshes}
    assert "gadget/sliver" not in names and names["gadget/speck"].collision == []
    assert len(names["gadget"].collision) == 2  # body hull + the whole object's hull (for the wire)
    for kind in ("screen", "soil", "tri"):
        (box,) = names[f"gadget/{kind}"].collision
        assert sorted(box.extents)[0] == pytest.approx(THIN_BOX_M)
    (floor,) = [m for m in scene.meshes if m.category == "floor"]
    (wall,) = [m for m in scene.meshes if m.category == "wall"]
    assert floor.collision == [] and len(wall.collision) == 1 and wall.collision[0].is_volume
    model = build_model(scene)  # compiles: no coplanar or collinear mesh reaches MuJoCo
    col = [i for i in range(model.ngeom) if model.geom_contype[i]]
    thin = [
        i for i in col if model.geom_type[i] == mujoco.mjtGeom.mjGEOM_BOX and model.geom_size[i].min() < 0.011
    ]
    assert len(thin) >= 3


def test_flat_collision_handed_to_the_model_becomes_a_thin_box() -> None:
    base = make_tiny_scene(with_boxes=False)
    quad = trimesh.Trimesh([[1, 1, 0.5], [2, 1, 0.5], [2, 2, 0.5], [1, 2, 0.5]], [[0, 1, 2], [0, 2, 3]])
    assert part_collision(quad)[1] == "flat"
    tiny = trimesh.creation.box(extents=(0.002, 0.002, 0.002))
    extra = SceneMesh("sheet", "box", quad, Material("grey"), [quad, tiny])
    model = build_model(Scene("flat", "base", "checker", [*base.meshes, extra]))
    sheet = [
        i
        for i in range(model.ngeom)
        if mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, i) == "col_sheet_0"
    ]
    assert len(sheet) == 1 and model.geom_type[sheet[0]] == mujoco.mjtGeom.mjGEOM_BOX
    assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "col_sheet_1") == -1  # tiny part dropped


def _tiny_mesh_scene(out):
    """The tests' tiny room exported as a mesh-scene directory (base + changed) plus the lamp OBJ."""
    base = make_tiny_scene()
    changed = Scene("tiny", "changed", base.texture, [m for m in base.meshes if m.name != "box_b"])
    export_mesh_scene([base, changed], out)
    _write_lamp(out / "objects" / "lamp")
    for f in ("layout.json", "layout_changed.json"):
        data = json.loads((out / f).read_text())
        data["objects"].append(
            {
                "name": "lamp",
                "mesh": "objects/lamp/lamp.obj",
                "bbox": {"centre": [3.5, 0.6, 0.6], "size": [0.5, 0.5, 1.2]},
            }
        )
        (out / f).write_text(json.dumps(data))
    return out


def test_digest_covers_layouts_meshes_mtl_and_textures(tmp_path) -> None:
    root = _tiny_mesh_scene(tmp_path / "tiny")
    d0 = mesh_scene_digest(root)
    (root / "notes.txt").write_text("unrelated")
    assert mesh_scene_digest(root) == d0
    for rel in (
        "objects/lamp/shade.png",
        "objects/lamp/lamp.mtl",
        "objects/lamp/lamp.obj",
        "layout_changed.json",
    ):
        f = root / rel
        keep = f.read_bytes()
        f.write_bytes(keep + b"\n")
        assert mesh_scene_digest(root) != d0, rel
        f.write_bytes(keep)
    assert mesh_scene_digest(root) == d0
    (root / "objects" / "lamp" / "missing_wood.jpg").write_bytes(b"now here")  # a missing file appears
    assert mesh_scene_digest(root) != d0


def test_changed_texture_rebuilds_and_summary_says_native(tmp_path) -> None:
    root = _tiny_mesh_scene(tmp_path / "tiny")
    out = tmp_path / "build"
    first = build_runs(str(root), out, size=(32, 24), progress=False)
    assert first["texture"] == "native" and first["database_frames"] > 20
    assert (
        build_runs(str(root), out, size=(32, 24), progress=False)["build_seconds"] == first["build_seconds"]
    )
    _write_lamp(root / "objects" / "lamp", shade_rgb=(20, 200, 40))
    again = build_runs(str(root), out, size=(32, 24), progress=False)
    assert again["parameters"]["source_sha256"] != first["parameters"]["source_sha256"]
    assert json.loads((out / "summary.json").read_text())["parameters"] == again["parameters"]
