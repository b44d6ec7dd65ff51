"""Scene specifications, procedural generation, meshes and MuJoCo models (vgpnav_env.scenes).

Public entry point: ``load_scene(source, layout, texture, lighting) -> Scene``.
"""

from vgpnav_env.scenes.lighting import LIGHTING_LEVELS, LIGHTING_PRESETS, LightingPreset
from vgpnav_env.scenes.materials import MATERIAL_KINDS, TEXTURE_LEVELS, make_material
from vgpnav_env.scenes.mesh_scene import export_mesh_scene, load_mesh_scene
from vgpnav_env.scenes.meshes import build_scene, object_of
from vgpnav_env.scenes.procedural import generate
from vgpnav_env.scenes.registry import (
    BUILTIN_SCENES,
    STYLES,
    list_layouts,
    load_scene,
    load_scene_spec,
    scene_slug,
)
from vgpnav_env.scenes.scene import Material, Scene, SceneMesh
from vgpnav_env.scenes.spec import SceneError, SceneSpec, load_spec, parse_spec

__all__ = [
    "BUILTIN_SCENES",
    "LIGHTING_LEVELS",
    "LIGHTING_PRESETS",
    "MATERIAL_KINDS",
    "STYLES",
    "TEXTURE_LEVELS",
    "LightingPreset",
    "Material",
    "Scene",
    "SceneError",
    "SceneMesh",
    "SceneSpec",
    "build_scene",
    "export_mesh_scene",
    "generate",
    "list_layouts",
    "load_scene",
    "load_mesh_scene",
    "load_scene_spec",
    "load_spec",
    "make_material",
    "object_of",
    "parse_spec",
    "scene_slug",
]
