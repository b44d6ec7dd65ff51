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
      structure.glb        walls + floor (+ ceiling), GLB/GLTF/OBJ(+MTL)/PLY
      objects/...          one mesh file per object (OBJ + MTL + textures, GLB, ...)

Everything in the JSON is in the file's own frame: an object mesh is centred on its bounds, scaled per
axis to ``size``, rotated by ``euler`` (extrinsic xyz, radians) and moved to ``centre``; then the whole
scene is converted to W: ``up: y`` files are rotated to z-up ((x, y, z) -> (x, -z, y)) and every
coordinate is multiplied by ``scale`` (e.g. 0.01 for centimetres).

Parts and appearance come from ``mesh_files.load_parts`` (one part per node / material, textures
found however the files name them, opacity kept). Structure parts without a category are
classified by shape: thin horizontal parts at the bottom are ``floor``, at the top ``ceiling``,
anything else ``wall``. Collision (``collision.py``, decided by a shape check): a watertight convex
wall component uses its hull, other wall surfaces a thin box per rectangular vertical facet (a thin
prism per triangle otherwise); floors, ceilings and trims none. Object parts: solid -> hull, flat ->
thin box, tiny -> none, degenerate -> the hull of the whole object. Every such fix and every file
that could not be found goes to the :class:`LoadReport` (``load_mesh_scene(..., report=True)``) and
to the log (fixes at INFO, missing files as one WARNING each).
"""

from __future__ import annotations

import hashlib
import json
import logging
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, overload

import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from vgpnav_env.scenes.collision import facet_boxes, is_convex_solid, object_collision, part_collision
from vgpnav_env.scenes.mesh_files import MeshPart, load_parts, referenced_files
from vgpnav_env.scenes.meshes import STRUCTURE_CATEGORIES
from vgpnav_env.scenes.scene import Scene, SceneMesh
from vgpnav_env.scenes.spec import SceneError, read_data_file

logger = logging.getLogger(__name__)

UP_AXES = ("z", "y")
_Y_TO_Z = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # file (y up) -> W (z up)
#: (file, name) of missing files already warned about in this process (one warning per file).
_WARNED: set[tuple[str, str]] = set()


@dataclass
class LoadReport:
    """What ``load_mesh_scene`` changed to make a directory usable, one line per item."""

    source: str
    layout: str
    fixes: list[str] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)

    def fix(self, line: str) -> None:
        self.fixes.append(line)
        logger.info("%s: %s", self.source, line)

    def miss(self, line: str) -> None:
        self.missing.append(line)
        logger.warning("%s: %s", self.source, line)

    def __str__(self) -> str:
        lines = [
            f"{self.source} (layout {self.layout}): {len(self.fixes)} fixes, {len(self.missing)} missing"
        ]
        return "\n".join(
            lines + [f"  missing: {m}" for m in self.missing] + [f"  fix: {f}" for f in self.fixes]
        )


def mesh_scene_layouts(path: str | Path) -> list[str]:
    """Layouts of a mesh-scene directory: ``base`` (layout.json) and every ``layout_<name>.json``."""
    p = Path(path)
    names = sorted(f.stem[len("layout_") :] for f in p.glob("layout_*.json"))
    return ["base"] + [n for n in names if n != "base"]


def _read_json(path: Path) -> dict[str, Any]:
    data = read_data_file(path, "JSON")
    if not isinstance(data, dict):
        raise SceneError(f"{path}: expected a JSON object with 'structure' and 'objects'")
    return data


def mesh_scene_files(path: str | Path) -> list[Path]:
    """Every file a mesh-scene directory's scenes depend on: ``layout*.json``, the structure and
    object mesh files they name, and the files those name (MTL libraries, textures, glTF buffers)."""
    root = Path(path)
    layouts = [root / "layout.json"] + sorted(root.glob("layout_*.json"))
    meshes: dict[Path, None] = {}
    for f in layouts:
        data = _read_json(f)
        if isinstance(data.get("structure"), str):
            meshes[root / data["structure"]] = None
        for o in data.get("objects", []) if isinstance(data.get("objects"), list) else []:
            if isinstance(o, dict) and isinstance(o.get("mesh"), str):
                meshes[root / o["mesh"]] = None
    files = list(layouts)
    for m in meshes:
        files.append(m)
        if m.is_file():
            files += referenced_files(m)[0]
    return list(dict.fromkeys(files))


def mesh_scene_digest(path: str | Path) -> str:
    """SHA-256 over :func:`mesh_scene_files` (names and contents; a missing file counts as missing)."""
    root = Path(path)
    h = hashlib.sha256()
    for f in mesh_scene_files(root):
        name = f.relative_to(root).as_posix() if f.is_relative_to(root) else str(f)
        content = hashlib.sha256(f.read_bytes()).hexdigest() if f.is_file() else "<missing>"
        h.update(f"{name}\0{content}\n".encode())
    return h.hexdigest()


def _load(path: Path, what: str, prefix: str, report: LoadReport, root: Path) -> list[MeshPart]:
    loaded = load_parts(path, what, prefix)
    rel = path.relative_to(root).as_posix() if path.is_relative_to(root) else str(path)
    for name in loaded.missing:
        if (rel, name) in _WARNED:  # another layout of the same files: warned already
            report.missing.append(f"{rel}: file {name!r} not found")
            continue
        _WARNED.add((rel, name))
        report.miss(
            f"{rel}: file {name!r} not found (looked beside the file, in any case and below its folder)"
        )
    for note in loaded.notes:
        report.fix(f"{rel}: {note}")
    return loaded.parts


def _file_to_world(up: str, scale: float) -> NDArray[np.float64]:
    """4x4 map from the files' frame and units to W."""
    T = np.eye(4)
    T[:3, :3] = (_Y_TO_Z if up == "y" else np.eye(3)) * scale
    return T


def _classify(m: trimesh.Trimesh, zmin: float, zmax: float) -> str:
    lo, hi = m.bounds
    if hi[2] - lo[2] < 0.1:
        if lo[2] < zmin + 0.2:
            return "floor"
        if hi[2] > zmax - 0.2:
            return "ceiling"
    return "wall"


def _wall_collision(name: str, m: trimesh.Trimesh, report: LoadReport) -> list[trimesh.Trimesh]:
    out: list[trimesh.Trimesh] = []
    open_parts = 0
    solid = trimesh.Trimesh(m.vertices, m.faces, process=True)  # vertices split at UV seams merged
    for c in solid.split(only_watertight=False) or [solid]:
        if is_convex_solid(c):
            out.append(trimesh.convex.convex_hull(c.vertices))
        else:
            open_parts += 1
            out += facet_boxes(c)
    if open_parts:
        report.fix(
            f"wall {name}: {open_parts} open or non-convex parts -> {len(out)} convex parts behind its faces"
        )
    return out


def _structure_meshes(
    parts: list[MeshPart], categories: dict[str, str], report: LoadReport
) -> list[SceneMesh]:
    pieces: list[MeshPart] = []
    for p in parts:
        if p.name in categories or len(parts) > 1:
            pieces.append(p)
            continue
        comps = p.mesh.split(only_watertight=False)
        if len(comps) > 1:
            pieces += [MeshPart(f"{p.name}_{i}", c, p.material) for i, c in enumerate(comps)]
        else:
            pieces.append(p)
    zmin = min(p.mesh.bounds[0, 2] for p in pieces)
    zmax = max(p.mesh.bounds[1, 2] for p in pieces)
    out = []
    for p in pieces:
        cat = categories.get(p.name) or _classify(p.mesh, zmin, zmax)
        mesh_name = p.name if p.name.startswith(f"{cat}/") else f"{cat}/{p.name}"
        collision = [] if cat in ("floor", "ceiling", "trim") else _wall_collision(mesh_name, p.mesh, report)
        out.append(SceneMesh(mesh_name, cat, p.mesh, p.material, collision))
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
    if np.any(size <= 0) or not np.all(np.isfinite(np.concatenate([centre, size, euler]))):
        raise SceneError(f"{where}: bbox size must be positive and finite, got {size.tolist()}")
    return centre, size, euler


def _object_meshes(
    root: Path, entry: dict, where: str, up: str, scale: float, report: LoadReport
) -> list[SceneMesh]:
    """The SceneMeshes of one layout object: ``<name>`` for its first part, ``<name>/<part>`` others."""
    centre, size, euler = _bbox(entry, where)
    name, cat = str(entry["name"]), str(entry.get("category", "object"))
    raw = _load(root / entry["mesh"], where, f"{root.name}/{name}/", report, root)
    lo = np.min([p.mesh.bounds[0] for p in raw], axis=0)
    hi = np.max([p.mesh.bounds[1] for p in raw], axis=0)
    flat_axes = hi - lo < 1e-9
    if flat_axes.any():
        report.fix(
            f"object {name}: zero extent along axes {np.flatnonzero(flat_axes).tolist()} -> not scaled there"
        )
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", euler).as_matrix() @ np.diag(
        np.where(flat_axes, 1.0, size / np.maximum(hi - lo, 1e-9))
    )
    T[:3, 3] = centre - T[:3, :3] @ ((lo + hi) / 2)
    world = [p.mesh.apply_transform(_file_to_world(up, scale) @ T) for p in raw]  # fresh meshes: in place
    collide = bool(entry.get("collision", True))
    out, whole = [], False
    for k, (p, mw) in enumerate(zip(raw, world, strict=True)):
        mesh_name = name if k == 0 else f"{name}/{p.name}"
        collision: list[trimesh.Trimesh] = []
        if collide:
            collision, kind, note = part_collision(mw)
            whole |= kind in ("line", "empty")
            if note:
                report.fix(f"{mesh_name}: {note}")
        out.append(SceneMesh(mesh_name, cat, mw, p.material, collision))
    if whole:
        out[0].collision = out[0].collision + object_collision(world)
    return out


@overload
def load_mesh_scene(path: str | Path, *args: Any, report: Literal[False] = ..., **kwargs: Any) -> Scene: ...
@overload
def load_mesh_scene(
    path: str | Path, *args: Any, report: Literal[True], **kwargs: Any
) -> tuple[Scene, LoadReport]: ...
def load_mesh_scene(
    path: str | Path,
    up: str | None = None,
    scale: float | None = None,
    layout: str = "base",
    *,
    report: bool = False,
) -> Scene | tuple[Scene, LoadReport]:
    """A mesh-scene directory as a ``Scene`` in W (texture level ``native``: the files' own appearance).

    ``report=True`` also returns the :class:`LoadReport` (every fix made, every file not found).
    """
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
    rep = LoadReport(str(root), layout)
    parts = _load(root / data["structure"], f"{root}: structure", f"{root.name}/structure/", rep, root)
    for p in parts:
        p.mesh.apply_transform(_file_to_world(up, scale))  # fresh meshes: in place
    meshes = _structure_meshes(parts, dict(data.get("structure_categories", {})), rep)
    objects = data.get("objects", [])
    if not isinstance(objects, list):
        raise SceneError(f"{root}: 'objects' must be a list")
    for i, entry in enumerate(objects):
        where = f"{root}: objects[{i}]"
        if not isinstance(entry, dict) or "name" not in entry or "mesh" not in entry:
            raise SceneError(f"{where}: needs 'name', 'mesh', 'bbox' (and optional 'category')")
        meshes += _object_meshes(root, entry, where, up, scale, rep)
    scene = Scene(name=root.name, layout=layout, texture="native", meshes=meshes)
    logger.info(
        "%s: loaded %d meshes, %d fixes, %d files missing",
        root,
        len(meshes),
        len(rep.fixes),
        len(rep.missing),
    )
    return (scene, rep) if report else scene


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
