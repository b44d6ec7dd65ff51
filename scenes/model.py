"""Scene -> MuJoCo model (``mujoco.MjSpec``), with textures, lights and collision parts.

Contract of the model built here:

- Every ``SceneMesh`` is one visual mesh geom in the world body: group 0, no contacts
  (contype = conaffinity = 0), texture coordinates from the mesh UVs (tiles, texrepeat 1).
  Its material's ``rgba`` multiplies the texture; alpha < 1 (glass) is drawn transparent.
  A surface without area is skipped (MuJoCo refuses it).
- Every convex collision part is one geom (a ``box`` where the part is a box, else a
  ``mesh``) in group ``COLLISION_GROUP`` (3, hidden by the renderers), contype =
  conaffinity = 1; a part that is not a full-dimensional solid becomes a thin box (flat) or
  is dropped (``collision.shape_of``), so the model always compiles. The floor has no
  collision part: a robot stands on it by its joints.
- A world camera ``RENDER_CAMERA`` that renderers place anywhere (``vgpnav_env.render``).
- Lights from ``vgpnav_env.scenes.lighting.LIGHTING_PRESETS[scene.lighting]``: the preset's
  ambient and diffuse headlight, and its ``room_diffuse`` as two tilted directional lights
  (``scene_lights``; not per-room point lights, which MuJoCo's per-vertex lighting draws badly
  on large triangles); no specular light, no light casts shadows.
- Clip planes: near ``ZNEAR_M`` metres, far beyond the scene diagonal.

Other code (e.g. the environment's robot) adds bodies to the ``MjSpec`` returned by
:func:`build_mjspec` before compiling it; robot geoms that the camera must not see go in
group ``COLLISION_GROUP`` too. :func:`build_model` compiles the bare scene and caches it.
"""

from __future__ import annotations

import logging
import weakref
from dataclasses import dataclass

import mujoco
import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from vgpnav_env.scenes.collision import shape_of, thin_box
from vgpnav_env.scenes.lighting import LIGHTING_PRESETS, LightingPreset
from vgpnav_env.scenes.scene import Material, Scene, SceneMesh

logger = logging.getLogger(__name__)

RENDER_CAMERA = "vgpnav_render"
VISUAL_GROUP = 0
COLLISION_GROUP = 3
ZNEAR_M = 0.05
#: Visual meshes with less area than this (m^2) are not drawn (MuJoCo refuses them).
MIN_AREA_M2 = 1e-12


#: Directions (W) of the two directional lights that carry a preset's ``room_diffuse`` (half each).
#: MuJoCo's classic renderer lights per vertex, so point lights over large triangles (floors,
#: walls) come out wrong; two opposite, tilted directional lights light floors evenly and every
#: wall orientation a little, the same in every room.
ROOM_LIGHT_DIRECTIONS = ((0.4, 0.25, -1.0), (-0.4, -0.25, -1.0))


@dataclass(frozen=True)
class DirectionalLight:
    """A light shining along ``direction`` (unit, W) with diffuse RGB."""

    direction: tuple[float, float, float]
    diffuse: tuple[float, float, float]


def lighting_for(name: str) -> LightingPreset:
    """The ``LightingPreset`` called ``name`` (clear error for unknown names)."""
    try:
        return LIGHTING_PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown lighting {name!r}; allowed: {sorted(LIGHTING_PRESETS)}") from None


def scene_lights(scene: Scene) -> list[DirectionalLight]:
    """The directional lights of ``scene`` (its preset's ``room_diffuse``, see ROOM_LIGHT_DIRECTIONS)."""
    preset = lighting_for(scene.lighting)
    diffuse = tuple(0.5 * c for c in preset.room_diffuse)
    lights = []
    for d in ROOM_LIGHT_DIRECTIONS:
        unit = np.asarray(d, float) / np.linalg.norm(d)
        lights.append(DirectionalLight(tuple(float(v) for v in unit), diffuse))
    return lights


def _unique_name(base: str, used: set[str]) -> str:
    name, i = base, 1
    while name in used:
        name, i = f"{base}_{i}", i + 1
    used.add(name)
    return name


def _add_material(spec: mujoco.MjSpec, material: Material, used: set[str]) -> str:
    """Add a MuJoCo material (and 2D texture if the material has an image); return its name."""
    name = _unique_name(f"mat_{material.name}", used)
    mat = spec.add_material(name=name)
    mat.rgba = np.asarray(material.rgba, float)
    mat.specular = float(material.specular)
    mat.shininess = float(material.shininess)
    mat.reflectance = 0.0
    if material.image is not None:
        image = np.ascontiguousarray(material.image, dtype=np.uint8)
        if image.ndim != 3 or image.shape[2] != 3:
            raise ValueError(
                f"material {material.name!r}: image must be uint8 HxWx3, got shape {image.shape}"
            )
        tex_name = _unique_name(f"tex_{material.name}", used)
        tex = spec.add_texture(name=tex_name, type=mujoco.mjtTexture.mjTEXTURE_2D)
        tex.width, tex.height, tex.nchannel = image.shape[1], image.shape[0], 3
        tex.data = image.tobytes()
        textures = list(mat.textures)
        textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = tex_name
        mat.textures = textures
        mat.texrepeat = [1.0, 1.0]
        mat.texuniform = False
    return name


def _mesh_uv(scene_mesh: SceneMesh) -> NDArray[np.float64] | None:
    uv = getattr(scene_mesh.mesh.visual, "uv", None)
    if uv is None or len(uv) != len(scene_mesh.mesh.vertices):
        if scene_mesh.material.image is not None:
            raise ValueError(
                f"mesh {scene_mesh.name!r} has a textured material but no per-vertex UVs "
                f"(got {None if uv is None else len(uv)} UVs for {len(scene_mesh.mesh.vertices)} vertices)"
            )
        return None
    return np.asarray(uv, float)


def _box_of(part: trimesh.Trimesh) -> tuple[NDArray, NDArray, NDArray] | None:
    """(half sizes, centre, quaternion wxyz) if ``part`` is a box, else None."""
    if len(part.vertices) != 8 or len(part.faces) != 12:
        return None
    obb = part.bounding_box_oriented
    if not np.isclose(obb.volume, abs(part.volume), rtol=1e-4, atol=1e-9):
        return None
    T = obb.primitive.transform
    quat_xyzw = Rotation.from_matrix(T[:3, :3]).as_quat()
    return np.asarray(obb.primitive.extents) / 2.0, T[:3, 3], np.roll(quat_xyzw, 1)


def _add_visual(spec: mujoco.MjSpec, sm: SceneMesh, material: str, used: set[str]) -> None:
    """One visual mesh geom; a surface MuJoCo cannot hold (no area) is skipped with a warning, and a
    single triangle gets a fourth (repeated, unused) vertex, as MuJoCo needs four."""
    vertices = np.asarray(sm.mesh.vertices, float)
    if len(sm.mesh.faces) == 0 or float(sm.mesh.area) <= MIN_AREA_M2:
        logger.warning("mesh %r has no surface area; not drawn", sm.name)
        return
    uv = _mesh_uv(sm)
    if len(vertices) < 4:
        vertices = np.concatenate([vertices, vertices[:1]])
        uv = None if uv is None else np.concatenate([uv, uv[:1]])
    mesh_name = _unique_name(f"vis_{sm.name}", used)
    mesh = spec.add_mesh(name=mesh_name)
    mesh.uservert = vertices.reshape(-1)
    mesh.userface = np.asarray(sm.mesh.faces, np.int32).reshape(-1)
    if uv is not None:
        # trimesh/OBJ UVs have v up from the image bottom; MuJoCo samples rows from the top.
        mesh.usertexcoord = np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=1).reshape(-1)
    mesh.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL
    geom = spec.worldbody.add_geom(
        name=_unique_name(sm.name, used),
        type=mujoco.mjtGeom.mjGEOM_MESH,
        meshname=mesh_name,
        material=material,
    )
    geom.contype = geom.conaffinity = 0
    geom.group = VISUAL_GROUP
    geom.mass = 0.0


def _collision_parts(sm: SceneMesh) -> list[trimesh.Trimesh]:
    """``sm.collision`` as parts MuJoCo compiles: boxes and solid hulls pass, a flat part becomes a thin
    box, a tiny or degenerate one is dropped (with a warning: loaders should not hand these over)."""
    out = []
    for part in sm.collision:
        shape = shape_of(part.vertices)
        if shape.kind == "solid":
            out.append(part)
        elif shape.kind == "flat":
            logger.warning("collision part of %r is flat; using a thin box", sm.name)
            out.append(thin_box(part.vertices, shape))
        else:
            logger.warning("collision part of %r is %s; dropped", sm.name, shape.kind)
    return out


def _add_collision(spec: mujoco.MjSpec, sm: SceneMesh, used: set[str]) -> None:
    for i, part in enumerate(_collision_parts(sm)):
        name = _unique_name(f"col_{sm.name}_{i}", used)
        box = _box_of(part)
        if box is not None:
            size, pos, quat = box
            geom = spec.worldbody.add_geom(
                name=name, type=mujoco.mjtGeom.mjGEOM_BOX, size=size, pos=pos, quat=quat
            )
        else:
            mesh_name = _unique_name(f"colmesh_{sm.name}_{i}", used)
            mesh = spec.add_mesh(name=mesh_name)
            mesh.uservert = np.asarray(part.vertices, float).reshape(-1)
            mesh.userface = np.asarray(part.faces, np.int32).reshape(-1)
            geom = spec.worldbody.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_MESH, meshname=mesh_name)
        geom.contype = geom.conaffinity = 1
        geom.group = COLLISION_GROUP
        geom.rgba = [0.5, 0.5, 0.5, 1.0]


def _add_lights(spec: mujoco.MjSpec, scene: Scene) -> None:
    preset = lighting_for(scene.lighting)
    head = spec.visual.headlight
    head.active = 1
    head.ambient = list(preset.ambient)
    head.diffuse = list(preset.headlight_diffuse)
    head.specular = [0.0, 0.0, 0.0]
    for i, light in enumerate(scene_lights(scene)):
        spec.worldbody.add_light(
            name=f"light_{i}",
            type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
            pos=[0.0, 0.0, 10.0],
            dir=list(light.direction),
            diffuse=list(light.diffuse),
            ambient=[0.0, 0.0, 0.0],
            specular=[0.0, 0.0, 0.0],
            castshadow=False,
        )


def build_mjspec(scene: Scene, *, max_image_size: tuple[int, int] = (640, 480)) -> mujoco.MjSpec:
    """Uncompiled ``MjSpec`` of ``scene`` (see module doc); add bodies, then ``spec.compile()``.

    ``max_image_size`` = (width, height): the largest image any renderer of this model draws.
    """
    if not scene.meshes:
        raise ValueError(f"scene {scene.key} has no meshes")
    width, height = (int(v) for v in max_image_size)
    if width <= 0 or height <= 0:
        raise ValueError(f"max_image_size must be positive (width, height), got {max_image_size}")
    spec = mujoco.MjSpec()
    spec.modelname = scene.key.replace("/", "_")
    spec.compiler.degree = False

    lo, hi = scene.bounds
    diagonal = float(np.linalg.norm(hi - lo))
    spec.stat.extent = max(diagonal, 1.0)
    spec.stat.center = (lo + hi) / 2.0
    spec.visual.map.znear = ZNEAR_M / spec.stat.extent
    spec.visual.map.zfar = (2.0 * diagonal + 10.0) / spec.stat.extent
    spec.visual.global_.offwidth = width
    spec.visual.global_.offheight = height
    spec.visual.quality.shadowsize = 0
    # No multisampling: a resolved MSAA depth buffer holds one sample's depth, not the pixel
    # centre's, which biases back-projected geometry by ~0.3 px (measured on llvmpipe).
    spec.visual.quality.offsamples = 0

    used: set[str] = set()
    materials: dict[int, str] = {}
    for sm in scene.meshes:
        key = id(sm.material)
        if key not in materials:
            materials[key] = _add_material(spec, sm.material, used)
        _add_visual(spec, sm, materials[key], used)
        _add_collision(spec, sm, used)

    _add_lights(spec, scene)
    spec.worldbody.add_camera(name=RENDER_CAMERA, pos=spec.stat.center, fovy=60.0)
    return spec


#: Per Scene object (by identity: hand-made scenes may share a ``key``), per max image size.
_MODEL_CACHE: weakref.WeakKeyDictionary[Scene, dict[tuple[int, int], mujoco.MjModel]] = (
    weakref.WeakKeyDictionary()
)


def build_model(scene: Scene, *, max_image_size: tuple[int, int] = (640, 480)) -> mujoco.MjModel:
    """Compiled model of ``scene`` alone, cached in-process per Scene object and max image size.

    The cached model is shared: renderers only change the ``RENDER_CAMERA`` pose and fovy.
    """
    size = (int(max_image_size[0]), int(max_image_size[1]))
    models = _MODEL_CACHE.setdefault(scene, {})
    model = models.get(size)
    if model is None:
        model = build_mjspec(scene, max_image_size=size).compile()
        logger.info("compiled MuJoCo model %s: %d geoms, %d textures", scene.key, model.ngeom, model.ntex)
        models[size] = model
    return model
