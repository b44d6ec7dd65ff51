"""Entry point: scene sources by name -> ``Scene``.

A source is a built-in name (``home``, ``hospital``), a procedural ``style:seed`` (``home:7``),
a path to a spec YAML file, or a path to a mesh-scene directory (``layout.json`` inside).
Built Scenes are cached in-process per arguments: treat them as read-only.
"""

from __future__ import annotations

import re
from functools import lru_cache
from pathlib import Path

from vgpnav_env.scenes.lighting import LIGHTING_LEVELS
from vgpnav_env.scenes.materials import TEXTURE_LEVELS
from vgpnav_env.scenes.meshes import build_scene
from vgpnav_env.scenes.scene import Scene
from vgpnav_env.scenes.spec import SceneError, SceneSpec, load_spec

BUILTIN_DIR = Path(__file__).parent / "builtin"
BUILTIN_SCENES: tuple[str, ...] = ("home", "hospital")
STYLES: tuple[str, ...] = ("home", "hospital")
_PROCEDURAL = re.compile(r"^(?P<style>[a-z]+):(?P<seed>\d+)$")

_ALLOWED = (
    f"a built-in name {list(BUILTIN_SCENES)}, 'style:seed' with style in {list(STYLES)} (e.g. 'home:7'), "
    "a spec .yaml file, or a mesh-scene directory containing layout.json"
)


def _kind(source: str) -> str:
    """'builtin' | 'procedural' | 'spec' | 'mesh' for a source string, or SceneError."""
    if source in BUILTIN_SCENES:
        return "builtin"
    m = _PROCEDURAL.match(source)
    if m:
        if m["style"] not in STYLES:
            raise SceneError(
                f"unknown procedural style {m['style']!r} in {source!r}; allowed: {list(STYLES)}"
            )
        return "procedural"
    p = Path(source)
    if p.is_dir():
        if not (p / "layout.json").is_file():
            raise SceneError(f"scene directory {source!r} has no layout.json; a source is {_ALLOWED}")
        return "mesh"
    if p.is_file() and p.suffix.lower() in (".yaml", ".yml"):
        return "spec"
    raise SceneError(f"unknown scene {source!r}; a source is {_ALLOWED}")


@lru_cache(maxsize=64)
def load_scene_spec(source: str) -> SceneSpec:
    """The spec of a built-in, procedural or YAML source (not for mesh-scene directories)."""
    kind = _kind(source)
    if kind == "builtin":
        return load_spec(BUILTIN_DIR / f"{source}.yaml")
    if kind == "procedural":
        from vgpnav_env.scenes.procedural import generate

        style, seed = source.split(":")
        return generate(style, int(seed))
    if kind == "spec":
        return load_spec(source)
    raise SceneError(f"{source!r} is a mesh-scene directory, which has no spec; use load_scene")


def list_layouts(source: str) -> list[str]:
    """Layout names of a source, ``base`` first."""
    if _kind(source) == "mesh":
        from vgpnav_env.scenes.mesh_scene import mesh_scene_layouts

        return mesh_scene_layouts(source)
    return load_scene_spec(source).layout_names


def scene_slug(source: str) -> str:
    """A filesystem-safe name for a source: ``home``, ``home-7``, or the file/directory stem."""
    kind = _kind(source)
    if kind == "builtin":
        return source
    if kind == "procedural":
        return source.replace(":", "-")
    p = Path(source).resolve()
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", p.stem if kind == "spec" else p.name)


def _check(value: str, allowed: tuple[str, ...], what: str) -> None:
    if value not in allowed:
        raise SceneError(f"unknown {what} {value!r}; allowed: {list(allowed)}")


@lru_cache(maxsize=32)
def load_scene(
    source: str, layout: str = "base", texture: str = "realistic", lighting: str = "default"
) -> Scene:
    """Build (or fetch from the in-process cache) one layout of a scene source.

    Mesh-scene directories keep their files' own appearance: ``texture`` is checked but the Scene's
    texture is ``native``.
    """
    _check(texture, TEXTURE_LEVELS, "texture level")
    _check(lighting, LIGHTING_LEVELS, "lighting")
    layouts = list_layouts(source)
    if layout not in layouts:
        raise SceneError(f"scene {source!r} has no layout {layout!r}; allowed: {layouts}")
    if _kind(source) == "mesh":
        from vgpnav_env.scenes.mesh_scene import load_mesh_scene

        scene = load_mesh_scene(source, layout=layout)
        scene.lighting = lighting
        return scene
    return build_scene(load_scene_spec(source), layout, texture, lighting)
