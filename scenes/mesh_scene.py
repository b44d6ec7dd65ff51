"""Bring-your-own mesh scenes (InternScenes-like directories) and their export.

Directory layout::

    scene_dir/
      layout.json          {"structure": "structure.glb", "up": "z"|"y", "scale": 1.0,
                            "structure_categories": {"<part>": "floor"|"ceiling"|"wall"|"trim"},
                            "objects": [{"name", "category", "mesh": "objects/x.glb",
                                         "bbox": {"centre": [x,y,z], "size": [sx,sy,sz],
                                                  "euler": [rx,ry,rz]},
                                         "collision": true}]}   # optional, false: visual only
      layout_<name>.json   further layouts: same keys; missing top-level keys come from layout.json
      structure.glb        walls + floor (+ ceiling), GLB/GLTF/OBJ/PLY
      objects/...          one mesh file per object

Everything in the JSON is in the file's own frame: an object mesh is centred on its bounds, scaled per
axis to ``size``, rotated by ``euler`` (extrinsic xyz, radians) and moved to ``centre``; then the whole
scene is converted to W: ``up: y`` files are rotated to z-up ((x, y, z) -> (x, -z, y)) and every
coordinate is multiplied by ``scale`` (e.g. 0.01 for centimetres).

Structure parts without a category are classified by shape: thin horizontal parts at the bottom are
``floor``, at the top ``ceiling``, anything else ``wall``. Collision: convex parts only -- a
watertight convex component uses its hull; other wall surfaces get a thin box per rectangular
vertical facet (a thin prism per triangle otherwise); objects use their convex hull.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from vgpnav_env.scenes.meshes import STRUCTURE_CATEGORIES, load_mesh_file
from vgpnav_env.scenes.scene import Material, Scene, SceneMesh
from vgpnav_env.scenes.spec import SceneError

UP_AXES = ("z", "y")
_Y_TO_Z = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # file (y up) -> W (z up)
WALL_SKIN_M = 0.05


def mesh_scene_layouts(path: str | Path) -> list[str]:
    """Layouts of a mesh-scene directory: ``base`` (layout.json) and every ``layout_<name>.json``."""
    p = Path(path)
    names = sorted(f.stem[len("layout_") :] for f in p.glob("layout_*.json"))
    return ["base"] + [n for n in names if n != "base"]


def _read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except OSError as e:
        raise SceneError(f"{path}: cannot read: {e}") from None
    except json.JSONDecodeError as e:
        raise SceneError(f"{path}: invalid JSON: {e}") from None
    if not isinstance(data, dict):
        raise SceneError(f"{path}: expected a JSON object with 'structure' and 'objects'")
    return data


def _load_parts(path: Path, what: str) -> list[tuple[str, trimesh.Trimesh]]:
    """(node name, mesh in the file frame) for every geometry in a mesh file."""
    if not path.is_file():
        raise SceneError(f"{what}: mesh file {path} does not exist")
    try:
        loaded = trimesh.load(str(path), process=False)
    except Exception as e:  # trimesh raises many exception types for bad files
        raise SceneError(f"{what}: cannot load mesh file {path}: {e}") from None
    if isinstance(loaded, trimesh.Trimesh):
        return [(path.stem, loaded)]
    if not isinstance(loaded, trimesh.Scene):
        return [(path.stem, load_mesh_file(path, what))]
    parts = []
    for node in loaded.graph.nodes_geometry:
        T, geom = loaded.graph[node]
        g = loaded.geometry[geom]
        if isinstance(g, trimesh.Trimesh) and len(g.faces):
            parts.append((str(node), g.copy().apply_transform(T)))
    if not parts:
        raise SceneError(f"{what}: mesh file {path} holds no triangles")
    return parts


def _material(mesh: trimesh.Trimesh, name: str) -> Material:
    """The mesh's own appearance as a Material (texture image with tile_m 1: its UVs are kept)."""
    vis = mesh.visual
    if isinstance(vis, trimesh.visual.TextureVisuals) and vis.material is not None:
        mat = vis.material
        img = getattr(mat, "baseColorTexture", None) or getattr(mat, "image", None)
        if img is not None and vis.uv is not None:
            image = np.asarray(img.convert("RGB"), dtype=np.uint8)
            mean = image.reshape(-1, 3).mean(axis=0) / 255.0
            return Material(name=name, rgba=(*map(float, mean), 1.0), image=image, tile_m=1.0)
        colour = getattr(mat, "baseColorFactor", None)
        if colour is None:
            colour = getattr(mat, "diffuse", None)
        if colour is not None:
            c = np.asarray(colour, float).ravel()[:4] / 255.0
            return Material(name=name, rgba=(float(c[0]), float(c[1]), float(c[2]), 1.0))
    if isinstance(vis, trimesh.visual.ColorVisuals) and vis.kind is not None:
        c = np.asarray(vis.main_color, float) / 255.0
        return Material(name=name, rgba=(float(c[0]), float(c[1]), float(c[2]), 1.0))
    return Material(name=name)


def _to_world(m: trimesh.Trimesh, up: str, scale: float) -> trimesh.Trimesh:
    T = np.eye(4)
    T[:3, :3] = (_Y_TO_Z if up == "y" else np.eye(3)) * scale
    return m.copy().apply_transform(T)


def _is_convex(m: trimesh.Trimesh) -> bool:
    if not m.is_watertight or m.volume <= 0:
        return False
    try:
        return bool(abs(m.volume) >= 0.97 * m.convex_hull.volume)
    except Exception:  # qhull fails on degenerate input
        return False


def _facet_boxes(m: trimesh.Trimesh) -> list[trimesh.Trimesh]:
    """Thin convex solids behind the vertical surfaces of a (possibly open, non-convex) wall mesh."""
    out = []
    vertical = np.abs(m.face_normals[:, 2]) < 0.3
    groups = [list(f) for f in m.facets] + [
        [i] for i in set(range(len(m.faces))) - {i for f in m.facets for i in f}
    ]
    for faces in groups:
        if not vertical[faces[0]]:
            continue
        n = m.face_normals[faces[0]]
        t1 = np.cross([0.0, 0.0, 1.0], n)
        t1 /= np.linalg.norm(t1)
        pts = m.vertices[m.faces[faces].ravel()]
        u, z = pts @ t1, pts[:, 2]
        area = float(m.area_faces[faces].sum())
        rect = (u.max() - u.min()) * (z.max() - z.min())
        if area < 1e-4:
            continue
        if area >= 0.95 * rect:
            centre = t1 * (u.max() + u.min()) / 2 + n * float(pts[0] @ n - WALL_SKIN_M / 2)
            centre[2] = (z.max() + z.min()) / 2
            T = np.eye(4)
            T[:3, :3] = np.column_stack([t1, n, [0.0, 0.0, 1.0]])
            T[:3, 3] = centre
            out.append(
                trimesh.creation.box(extents=(u.max() - u.min(), WALL_SKIN_M, z.max() - z.min()), transform=T)
            )
        else:
            for f in faces:
                tri = m.vertices[m.faces[f]]
                out.append(
                    trimesh.Trimesh(np.concatenate([tri, tri - n * WALL_SKIN_M]), process=True).convex_hull
                )
    return out


def _hull(m: trimesh.Trimesh) -> list[trimesh.Trimesh]:
    try:
        return [m.convex_hull]
    except Exception:  # flat or degenerate: fall back to the bounding box
        lo, hi = m.bounds
        T = np.eye(4)
        T[:3, 3] = (lo + hi) / 2
        return [trimesh.creation.box(extents=np.maximum(hi - lo, 0.01), transform=T)]


def _classify(m: trimesh.Trimesh, zmin: float, zmax: float) -> str:
    lo, hi = m.bounds
    if hi[2] - lo[2] < 0.1:
        if lo[2] < zmin + 0.2:
            return "floor"
        if hi[2] > zmax - 0.2:
            return "ceiling"
    return "wall"


def _structure_meshes(
    parts: list[tuple[str, trimesh.Trimesh]], categories: dict[str, str], tag: str
) -> list[SceneMesh]:
    pieces: list[tuple[str, trimesh.Trimesh]] = []
    for name, m in parts:
        if name in categories or len(parts) > 1:
            pieces.append((name, m))
        else:
            comps = m.split(only_watertight=False)
            pieces += [(f"{name}_{i}", c) for i, c in enumerate(comps)] if len(comps) > 1 else [(name, m)]
    zmin = min(m.bounds[0, 2] for _, m in pieces)
    zmax = max(m.bounds[1, 2] for _, m in pieces)
    out = []
    for name, m in pieces:
        cat = categories.get(name) or _classify(m, zmin, zmax)
        if cat in ("floor", "ceiling", "trim"):
            collision: list[trimesh.Trimesh] = []
        else:
            comps = m.split(only_watertight=False) or [m]
            collision = [h for c in comps for h in (_hull(c) if _is_convex(c) else _facet_boxes(c))]
        mesh_name = name if name.startswith(f"{cat}/") else f"{cat}/{name}"
        out.append(SceneMesh(mesh_name, cat, m, _material(m, f"{tag}/{mesh_name}"), collision))
    return out


def _bbox(entry: dict, where: str) -> tuple[NDArray, NDArray, NDArray]:
    b = entry.get("bbox")
    if not isinstance(b, dict):
        raise SceneError(f"{where}: missing 'bbox' {{'centre', 'size', 'euler'}}")
    try:
        centre = np.asarray(b["centre"], float).reshape(3)
        size = np.asarray(b["size"], float).reshape(3)
        euler = np.asarray(b.get("euler", [0, 0, 0]), float).reshape(3)
    except (KeyError, ValueError, TypeError) as e:
        raise SceneError(
            f"{where}: bbox needs 'centre' and 'size' as 3 numbers (and optional 'euler'): {e}"
        ) from None
    if np.any(size <= 0):
        raise SceneError(f"{where}: bbox size must be positive, got {size.tolist()}")
    return centre, size, euler


def load_mesh_scene(
    path: str | Path, up: str | None = None, scale: float | None = None, layout: str = "base"
) -> Scene:
    """A mesh-scene directory as a ``Scene`` in W (texture level ``native``: the files' own appearance)."""
    root = Path(path)
    main = _read_json(root / "layout.json")
    if layout == "base":
        data = main
    else:
        f = root / f"layout_{layout}.json"
        if not f.is_file():
            raise SceneError(f"{root}: no layout {layout!r}; allowed: {mesh_scene_layouts(root)}")
        data = {**main, **_read_json(f)}
    up = up or str(data.get("up", "z"))
    if up not in UP_AXES:
        raise SceneError(f"{root}: up axis {up!r} not allowed; allowed: {list(UP_AXES)}")
    scale = float(scale if scale is not None else data.get("scale", 1.0))
    if not scale > 0:
        raise SceneError(f"{root}: scale must be positive, got {scale}")
    if "structure" not in data:
        raise SceneError(f"{root}/layout.json: missing 'structure' (the walls + floor mesh file)")
    tag = root.name
    parts = [
        (n, _to_world(m, up, scale)) for n, m in _load_parts(root / data["structure"], f"{root}: structure")
    ]
    meshes = _structure_meshes(parts, dict(data.get("structure_categories", {})), tag)
    objects = data.get("objects", [])
    if not isinstance(objects, list):
        raise SceneError(f"{root}: 'objects' must be a list")
    for i, entry in enumerate(objects):
        where = f"{root}: objects[{i}]"
        if not isinstance(entry, dict) or "name" not in entry or "mesh" not in entry:
            raise SceneError(f"{where}: needs 'name', 'mesh', 'bbox' (and optional 'category')")
        centre, size, euler = _bbox(entry, where)
        raw = _load_parts(root / entry["mesh"], where)
        lo = np.min([m.bounds[0] for _, m in raw], axis=0)
        hi = np.max([m.bounds[1] for _, m in raw], axis=0)
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("xyz", euler).as_matrix() @ np.diag(size / np.maximum(hi - lo, 1e-9))
        T[:3, 3] = centre - T[:3, :3] @ ((lo + hi) / 2)
        for k, (pname, m) in enumerate(raw):
            mw = _to_world(m.copy().apply_transform(T), up, scale)
            name = str(entry["name"]) if k == 0 else f"{entry['name']}/{pname}"
            cat = str(entry.get("category", "object"))
            collision = _hull(mw) if entry.get("collision", True) else []
            meshes.append(SceneMesh(name, cat, mw, _material(mw, f"{tag}/{name}"), collision))
    return Scene(name=tag, layout=layout, texture="native", meshes=meshes)


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name)


def _from_world(m: trimesh.Trimesh, up: str, scale: float) -> trimesh.Trimesh:
    T = np.eye(4)
    T[:3, :3] = (_Y_TO_Z.T if up == "y" else np.eye(3)) / scale
    return m.copy().apply_transform(T)


def export_mesh_scene(
    scenes: Scene | list[Scene], out_dir: str | Path, up: str = "z", scale: float = 1.0
) -> Path:
    """Write scenes (layouts of one scene, the first is ``base``) as a mesh-scene directory.

    The structure (floor, ceiling, wall and trim meshes) comes from the first scene; each scene's objects go
    to ``objects/<layout>/<mesh>.glb`` with an axis-aligned bbox (euler 0) in the file frame. GLB
    files keep UVs and textures. Returns the directory.
    """
    scenes = [scenes] if isinstance(scenes, Scene) else list(scenes)
    if up not in UP_AXES or not scale > 0:
        raise SceneError(f"export: up must be one of {list(UP_AXES)} and scale > 0, got {up!r}, {scale}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    structure = trimesh.Scene()
    categories = {}
    for m in scenes[0].meshes:
        if m.category in STRUCTURE_CATEGORIES:
            structure.add_geometry(_from_world(m.mesh, up, scale), node_name=m.name, geom_name=m.name)
            categories[m.name] = m.category
    structure.export(out / "structure.glb")
    for i, sc in enumerate(scenes):
        objects = []
        for m in sc.meshes:
            if m.category in STRUCTURE_CATEGORIES:
                continue
            local = _from_world(m.mesh, up, scale)
            lo, hi = local.bounds
            centre = (lo + hi) / 2
            local.apply_translation(-centre)
            rel = Path("objects") / _safe(sc.layout) / f"{_safe(m.name)}.glb"
            (out / rel).parent.mkdir(parents=True, exist_ok=True)
            local.export(out / rel)
            bbox = {"centre": centre.tolist(), "size": (hi - lo).tolist(), "euler": [0.0, 0.0, 0.0]}
            objects.append(
                {
                    "name": m.name,
                    "category": m.category,
                    "mesh": rel.as_posix(),
                    "bbox": bbox,
                    "collision": bool(m.collision),
                }
            )
        data: dict[str, Any] = {"objects": objects}
        if i == 0:
            data = {
                "name": sc.name,
                "structure": "structure.glb",
                "up": up,
                "scale": scale,
                "structure_categories": categories,
                **data,
            }
        (out / ("layout.json" if i == 0 else f"layout_{_safe(sc.layout)}.json")).write_text(
            json.dumps(data, indent=1)
        )
    return out
