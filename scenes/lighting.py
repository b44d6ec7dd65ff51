"""Lighting presets named by ``Scene.lighting``; the MuJoCo model builder and renderers read them.

Meaning (agreed with ``scenes/model.py``, see ``docs/scenes.md``): a uniform ``ambient`` term, a
camera ``headlight_diffuse``, and ``room_diffuse``, the diffuse light of the room lights (the
MuJoCo model splits it over two tilted directional lights from above). No specular light, no
shadows. ``dim`` is a darker query condition, ``warm`` a yellowish (tungsten-like) one, ``bright``
a brighter one; ``default`` is what database runs use.
"""

from __future__ import annotations

from dataclasses import dataclass

RGB = tuple[float, float, float]


@dataclass(frozen=True)
class LightingPreset:
    """Light colours/intensities (linear RGB in [0, 1]) for one lighting condition."""

    ambient: RGB
    room_diffuse: RGB
    headlight_diffuse: RGB


LIGHTING_PRESETS: dict[str, LightingPreset] = {
    "default": LightingPreset(
        ambient=(0.48, 0.48, 0.48), room_diffuse=(0.62, 0.62, 0.62), headlight_diffuse=(0.3, 0.3, 0.3)
    ),
    "dim": LightingPreset(
        ambient=(0.18, 0.18, 0.18), room_diffuse=(0.25, 0.25, 0.25), headlight_diffuse=(0.1, 0.1, 0.1)
    ),
    "warm": LightingPreset(
        ambient=(0.36, 0.31, 0.24), room_diffuse=(0.5, 0.42, 0.3), headlight_diffuse=(0.2, 0.17, 0.13)
    ),
    "bright": LightingPreset(
        ambient=(0.55, 0.55, 0.55), room_diffuse=(0.65, 0.65, 0.65), headlight_diffuse=(0.35, 0.35, 0.35)
    ),
}

LIGHTING_LEVELS: tuple[str, ...] = tuple(LIGHTING_PRESETS)
