"""In-memory scene: world-frame meshes with materials, the contract between scene sources
(built-in specs, procedural generator, mesh files) and consumers (MuJoCo model, renderers,
ground truth).

All meshes are in W (metres, z up, floor at z = 0). Texture coordinates are in tiles:
``uv = surface coordinates in metres / material.tile_m`` so the texture repeats every
``tile_m`` metres on every face.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh
from numpy.typing import NDArray


@dataclass(frozen=True, eq=False)
class Material:
    """Appearance of a surface. ``image`` is uint8 HxWx3 RGB (None: plain ``rgba``)."""

    name: str
    rgba: tuple[float, float, float, float] = (0.8, 0.8, 0.8, 1.0)
    image: NDArray[np.uint8] | None = None
    tile_m: float = 1.0
    specular: float = 0.05
    shininess: float = 0.1


@dataclass(eq=False)
class SceneMesh:
    """One named object surface in W, with its category, material and convex collision parts.

    ``mesh.visual`` is a ``trimesh.visual.TextureVisuals`` carrying per-vertex UVs (in tiles)
    whenever ``material.image`` is set. ``collision`` holds convex meshes in W (may be empty
    for purely visual surfaces such as the floor, which the robot stands on).
    """

    name: str
    category: str
    mesh: trimesh.Trimesh
    material: Material
    collision: list[trimesh.Trimesh] = field(default_factory=list)


@dataclass(eq=False)
class Scene:
    """A layout of a scene ready to be turned into a MuJoCo model or rendered.

    ``key`` identifies the source and every parameter that changes geometry or appearance
    (e.g. ``home/base/realistic``); it names caches.
    """

    name: str
    layout: str
    texture: str
    meshes: list[SceneMesh]
    lighting: str = "default"

    @property
    def key(self) -> str:
        return f"{self.name}/{self.layout}/{self.texture}/{self.lighting}"

    @property
    def bounds(self) -> NDArray[np.float64]:
        """Axis-aligned bounds (2, 3) of all meshes in W."""
        corners = np.concatenate([m.mesh.bounds for m in self.meshes], axis=0)
        return np.stack([corners.min(axis=0), corners.max(axis=0)])

    def mesh(self, name: str) -> SceneMesh:
        for m in self.meshes:
            if m.name == name:
                return m
        raise KeyError(f"scene {self.key} has no mesh named {name!r}")
