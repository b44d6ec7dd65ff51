"""Spec + layout + texture level -> ``Scene``: textured trimesh surfaces in W with convex collision.

Mesh names: ``floor/<room>``, ``ceiling/<room>``, ``wall/<wall>``, ``trim/<wall>`` (skirting boards
and door architraves), and per object ``<object>`` for its main part plus ``<object>/<role>`` for its
other material roles (``object_of`` maps a mesh name back to its object). Categories: ``floor``,
``ceiling``, ``wall``, ``trim`` and the objects' categories. Floors and ceilings are 2 cm slabs
(floor top at z = 0, ceiling bottom at the wall height); they and trims have no collision; walls and
objects carry convex collision parts (boxes, cylinders, convex hulls).

UVs are isometric per face: each face is projected onto an orthonormal basis of its own plane
(u horizontal, v up on vertical faces) in the object's local frame, divided by ``tile_m``, so a
texture tile always covers ``tile_m`` metres and never stretches on narrow faces.
"""

from __future__ import annotations

import logging
import math
import zlib
from pathlib import Path

import numpy as np
import trimesh
from numpy.typing import NDArray
from PIL import Image

from vgpnav_env.geometry import make_pose
from vgpnav_env.scenes.collision import object_collision
from vgpnav_env.scenes.materials import make_material
from vgpnav_env.scenes.mesh_files import load_parts
from vgpnav_env.scenes.primitives import FITTED_ROLES, Part, primitive_parts, role_materials
from vgpnav_env.scenes.scene import Material, Scene, SceneMesh
from vgpnav_env.scenes.spec import ObjectSpec, RoomSpec, SceneError, SceneSpec, WallSpec

SLAB_M = 0.02
STRUCTURE_CATEGORIES = ("floor", "ceiling", "wall", "trim")
TRIM_MATERIAL = "wood:white"

logger = logging.getLogger(__name__)


def object_of(mesh_name: str) -> str:
    """The object (or structure element) a mesh belongs to: ``sofa/cushion`` -> ``sofa``."""
    head, _, rest = mesh_name.partition("/")
    return mesh_name if head in STRUCTURE_CATEGORIES else head


def planar_uv(mesh: trimesh.Trimesh, tile_m: float, fit: bool = False) -> tuple[NDArray, NDArray, NDArray]:
    """Unmerged (vertices, faces, uv) with per-face isometric UVs in tiles.

    Horizontal faces use (x, y); other faces use (horizontal tangent, z-projected up) of their plane.
    ``fit`` shifts each planar group so its UVs start at 0 (one image fitted to a face).
    """
    tri = mesh.vertices[mesh.faces]  # (F, 3, 3)
    n = mesh.face_normals
    up = np.array([0.0, 0.0, 1.0])
    horizontal = np.abs(n[:, 2]) > 0.7
    t1 = np.cross(up, n)
    t1[horizontal] = (1.0, 0.0, 0.0)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    uv = np.stack([np.einsum("fkj,fj->fk", tri, t1), np.einsum("fkj,fj->fk", tri, t2)], axis=-1) / tile_m
    if fit:
        keys = np.round(n, 3)
        _, group = np.unique(keys, axis=0, return_inverse=True)
        for g in np.unique(group):
            sel = group.ravel() == g
            uv[sel] -= uv[sel].reshape(-1, 2).min(axis=0)
    vertices = tri.reshape(-1, 3)
    faces = np.arange(len(vertices)).reshape(-1, 3)
    return vertices, faces, uv.reshape(-1, 2)


def textured(
    mesh_local: trimesh.Trimesh, material: Material, T_wl: NDArray | None = None, fit: bool = False
) -> trimesh.Trimesh:
    """Copy of a local-frame mesh with isometric UVs and the material's texture, moved into W by ``T_wl``."""
    v, f, uv = planar_uv(mesh_local, material.tile_m, fit)
    if T_wl is not None:
        v = v @ T_wl[:3, :3].T + T_wl[:3, 3]
    return with_texture(trimesh.Trimesh(v, f, process=False), uv, material)


def with_texture(mesh: trimesh.Trimesh, uv: NDArray, material: Material) -> trimesh.Trimesh:
    """Attach ``TextureVisuals`` (uv in tiles, the material's image) to a mesh in place and return it.

    The glTF material says what MuJoCo draws: ``baseColorFactor`` = ``material.rgba``, which
    multiplies the texture (``alphaMode`` BLEND below full opacity).
    """
    image = Image.fromarray(np.asarray(material.image)) if material.image is not None else None
    mat = trimesh.visual.material.PBRMaterial(
        name=material.name,
        baseColorTexture=image,
        baseColorFactor=np.round(np.asarray(material.rgba) * 255).astype(np.uint8),
        metallicFactor=0.0,
        roughnessFactor=0.9,
        alphaMode="BLEND" if material.rgba[3] < 1.0 else "OPAQUE",
    )
    mesh.visual = trimesh.visual.TextureVisuals(uv=uv, material=mat)
    return mesh


def _part_mesh(part: Part) -> trimesh.Trimesh:
    T = np.eye(4)
    T[:3, 3] = part.centre
    if part.shape == "box":
        return trimesh.creation.box(extents=part.size, transform=T)
    return trimesh.creation.cylinder(radius=part.size[0] / 2, height=part.size[2], sections=20, transform=T)


def _concat(meshes: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    """Concatenate meshes sharing one material, keeping UVs and the texture."""
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    out = trimesh.Trimesh(
        np.concatenate([m.vertices for m in meshes]),
        np.concatenate([m.faces + k for m, k in zip(meshes, offsets, strict=True)]),
        process=False,
    )
    out.visual = trimesh.visual.TextureVisuals(
        uv=np.concatenate([m.visual.uv for m in meshes]), material=meshes[0].visual.material
    )
    return out


def _object_pose(o: ObjectSpec) -> NDArray:
    c, s = math.cos(o.yaw), math.sin(o.yaw)
    return make_pose(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]), (o.x, o.y, o.z))


def _seed(spec_seed: int, name: str) -> int:
    return (spec_seed * 1_000_003 + zlib.crc32(name.encode())) & 0x7FFFFFFF


def _primitive_meshes(o: ObjectSpec, level: str, spec_seed: int) -> list[SceneMesh]:
    size, parts = primitive_parts(o.kind, o.size)
    mats = role_materials(o.kind, o.material, dict(o.materials))
    T = _object_pose(o)
    roles = list(dict.fromkeys(p.role for p in parts))
    primary = "main" if "main" in roles else roles[0]
    out = []
    for role in roles:
        rparts = [p for p in parts if p.role == role]
        fit = role in FITTED_ROLES
        if fit or role == "books":
            tile = max(rparts[0].size[0], rparts[0].size[2]) if fit else None
            material = make_material(mats[role], level, _seed(spec_seed, o.name), tile)
        else:
            material = make_material(mats[role], level, spec_seed)
        surf = _concat([textured(_part_mesh(p), material, T, fit) for p in rparts])
        collision = [_part_mesh(p).apply_transform(T) for p in rparts if p.collide]
        name = o.name if role == primary else f"{o.name}/{role}"
        out.append(
            SceneMesh(name=name, category=o.category, mesh=surf, material=material, collision=collision)
        )
    return out


def _mesh_object(o: ObjectSpec, spec: SceneSpec, level: str) -> list[SceneMesh]:
    """A ``mesh:`` object: every part of the file (one per material) fitted together into ``size``
    (centred on x/y, base at z = 0); parts with their own texture keep it and their UVs, the others
    get ``material`` box-projected; one convex collision part (checked) for the whole object."""
    path = Path(spec.base_dir) / str(o.mesh)
    what = f"{spec.source}: object {o.name!r}"
    loaded = load_parts(path, what, f"mesh:{o.name}/")
    for name in loaded.missing:
        logger.warning("%s: file %r named in %s not found; plain colour used", what, name, path)
    lo = np.min([p.mesh.bounds[0] for p in loaded.parts], axis=0)
    hi = np.max([p.mesh.bounds[1] for p in loaded.parts], axis=0)
    scale = np.asarray(o.size, float) / np.maximum(hi - lo, 1e-9)
    offset = -np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    T = _object_pose(o)
    fallback = make_material(o.material or "plastic:grey", level, spec.seed)
    out = []
    for k, p in enumerate(loaded.parts):
        local = trimesh.Trimesh((p.mesh.vertices + offset) * scale, p.mesh.faces, process=False)
        material = p.material if p.material.image is not None else fallback
        if p.material.image is not None:
            surf = with_texture(local.apply_transform(T), np.asarray(p.mesh.visual.uv, float), material)
        else:
            surf = textured(local, material, T)
        name = o.name if k == 0 else f"{o.name}/{p.name}"
        out.append(SceneMesh(name=name, category=o.category, mesh=surf, material=material))
    out[0].collision = object_collision([m.mesh for m in out])
    return out


def _triangulate(poly: NDArray) -> NDArray:
    """Ear-clipping triangulation of a simple polygon (N, 2) -> (N-2, 3) vertex indices."""
    area = 0.5 * np.sum(poly[:, 0] * np.roll(poly[:, 1], -1) - np.roll(poly[:, 0], -1) * poly[:, 1])
    idx = list(range(len(poly))) if area > 0 else list(range(len(poly)))[::-1]
    tris = []

    def cross(o: NDArray, a: NDArray, b: NDArray) -> float:
        return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))

    while len(idx) > 3:
        for k in range(len(idx)):
            i0, i1, i2 = idx[k - 1], idx[k], idx[(k + 1) % len(idx)]
            a, b, c = poly[i0], poly[i1], poly[i2]
            if cross(a, b, c) <= 1e-12:
                continue
            others = [poly[j] for j in idx if j not in (i0, i1, i2)]
            if any(cross(a, b, p) >= 0 and cross(b, c, p) >= 0 and cross(c, a, p) >= 0 for p in others):
                continue
            tris.append((i0, i1, i2))
            idx.pop(k)
            break
        else:
            raise ValueError("polygon is not simple (self-intersecting or degenerate)")
    tris.append(tuple(idx))
    return np.asarray(tris, dtype=np.int64)


def _slab(room: RoomSpec, z_top: float, material: Material) -> trimesh.Trimesh:
    poly = np.asarray(room.polygon, float)
    try:
        faces = _triangulate(poly)
    except ValueError as e:
        raise SceneError(f"room {room.name!r}: {e}") from None
    m = trimesh.creation.extrude_triangulation(poly, faces, SLAB_M)
    m.apply_translation((0, 0, z_top - SLAB_M))
    return textured(m, material)


def _wall_pieces(w: WallSpec) -> list[tuple[float, float, float, float]]:
    """Solid pieces (a0, a1, z0, z1) along the wall (metres from its start)."""
    pieces, a = [], 0.0
    for d in w.doors:
        lo, hi = d.at - d.width / 2, d.at + d.width / 2
        if lo - a > 1e-6:
            pieces.append((a, lo, 0.0, w.height))
        if w.height - d.height > 1e-6:
            pieces.append((lo, hi, d.height, w.height))
        a = hi
    if w.length - a > 1e-6:
        pieces.append((a, w.length, 0.0, w.height))
    return pieces


def _wall_pose(w: WallSpec) -> NDArray:
    """T_w,wall: the wall's local frame (x along the wall from its start, y across, z up) in W."""
    yaw = math.atan2(w.end[1] - w.start[1], w.end[0] - w.start[0])
    c, s = math.cos(yaw), math.sin(yaw)
    return make_pose(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]), (w.start[0], w.start[1], 0.0))


def _local_box(a0: float, a1: float, y: float, depth: float, z0: float, z1: float) -> trimesh.Trimesh:
    T = np.eye(4)
    T[:3, 3] = ((a0 + a1) / 2, y, (z0 + z1) / 2)
    return trimesh.creation.box(extents=(a1 - a0, depth, z1 - z0), transform=T)


def _wall_mesh(w: WallSpec, material: Material) -> SceneMesh:
    T = _wall_pose(w)
    boxes = [_local_box(a0, a1, 0.0, w.thickness, z0, z1) for a0, a1, z0, z1 in _wall_pieces(w)]
    surf = _concat([textured(b, material, T) for b in boxes])
    collision = [b.copy().apply_transform(T) for b in boxes]
    return SceneMesh(
        name=f"wall/{w.name}", category="wall", mesh=surf, material=material, collision=collision
    )


SKIRTING_M = (0.08, 0.012)  # height, depth
ARCHITRAVE_M = (0.07, 0.015)  # width, depth


def _trim_mesh(w: WallSpec, material: Material) -> SceneMesh:
    """Skirting boards along both faces and architraves around door gaps (visual only)."""
    boxes = []
    for side in (-1.0, 1.0):
        sk_h, sk_d = SKIRTING_M
        for a0, a1, z0, _ in _wall_pieces(w):
            if z0 == 0.0:
                boxes.append(_local_box(a0, a1, side * (w.thickness + sk_d) / 2, sk_d, 0.0, sk_h))
        ar_w, ar_d = ARCHITRAVE_M
        y = side * (w.thickness + ar_d) / 2
        for d in w.doors:
            lo, hi = d.at - d.width / 2, d.at + d.width / 2
            if lo - ar_w >= 0.0:
                boxes.append(_local_box(lo - ar_w, lo, y, ar_d, 0.0, d.height + ar_w))
            if hi + ar_w <= w.length:
                boxes.append(_local_box(hi, hi + ar_w, y, ar_d, 0.0, d.height + ar_w))
            if d.height + ar_w <= w.height:
                boxes.append(
                    _local_box(
                        max(lo - ar_w, 0.0), min(hi + ar_w, w.length), y, ar_d, d.height, d.height + ar_w
                    )
                )
    surf = _concat([textured(b, material, _wall_pose(w)) for b in boxes])
    return SceneMesh(name=f"trim/{w.name}", category="trim", mesh=surf, material=material)


def build_scene(
    spec: SceneSpec, layout: str = "base", texture: str = "realistic", lighting: str = "default"
) -> Scene:
    """Meshes of one layout of a spec at a texture level (see the module docstring for names)."""
    objects = spec.layout_objects(layout)
    meshes: list[SceneMesh] = []
    ceiling_z = max((w.height for w in spec.walls), default=2.6)
    for room in spec.rooms:
        fm = make_material(room.floor, texture, spec.seed)
        meshes.append(SceneMesh(f"floor/{room.name}", "floor", _slab(room, 0.0, fm), fm))
        cm = make_material(room.ceiling, texture, spec.seed)
        meshes.append(SceneMesh(f"ceiling/{room.name}", "ceiling", _slab(room, ceiling_z + SLAB_M, cm), cm))
    for w in spec.walls:
        meshes.append(_wall_mesh(w, make_material(w.material, texture, spec.seed)))
        meshes.append(_trim_mesh(w, make_material(TRIM_MATERIAL, texture, spec.seed)))
    for o in objects:
        if o.kind == "mesh":
            meshes.extend(_mesh_object(o, spec, texture))
        else:
            meshes.extend(_primitive_meshes(o, texture, spec.seed))
    return Scene(name=spec.name, layout=layout, texture=texture, meshes=meshes, lighting=lighting)
