"""Feed-forward reconstruction backbones (DESIGN.md, Perception step 3) and their registry.

``make_backbone(name, **options)`` builds ``classical`` (default, pixels only),
``simulated`` (PRIVILEGED ground truth + noise) or ``learned`` (local weights only).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from vgpnav_env.perception.backbones.base import Backbone, BackboneOutput, Privileged
from vgpnav_env.perception.backbones.classical import ClassicalBackbone, ClassicalConfig, FeatureCache
from vgpnav_env.perception.backbones.simulated import SimulatedBackbone, SimulatedConfig

__all__ = [
    "BACKBONES",
    "Backbone",
    "BackboneOutput",
    "ClassicalBackbone",
    "ClassicalConfig",
    "FeatureCache",
    "Privileged",
    "SimulatedBackbone",
    "SimulatedConfig",
    "make_backbone",
]


def _classical(
    config: ClassicalConfig | None = None, feature_cache: FeatureCache | None = None, **knobs: Any
):
    if config is not None and knobs:
        raise ValueError("give either `config` or individual ClassicalConfig fields, not both")
    return ClassicalBackbone(config or ClassicalConfig(**knobs), feature_cache)


def _simulated(config: SimulatedConfig | None = None, seed: Any = None, **knobs: Any):
    if config is not None and knobs:
        raise ValueError("give either `config` or individual SimulatedConfig fields, not both")
    return SimulatedBackbone(config or SimulatedConfig(**knobs), seed)


def _learned(**options: Any):
    # Imported lazily: torch loads only when a learned backbone is asked for.
    from vgpnav_env.perception.backbones.learned import LearnedBackbone

    return LearnedBackbone(**options)


BACKBONES: dict[str, Callable[..., Backbone]] = {
    "classical": _classical,
    "simulated": _simulated,
    "learned": _learned,
}


def make_backbone(name: str = "classical", **options: Any) -> Backbone:
    """Build a backbone by name; ``options`` are its config fields or constructor arguments."""
    if name not in BACKBONES:
        raise ValueError(f"unknown backbone {name!r}; choose one of {sorted(BACKBONES)}")
    return BACKBONES[name](**options)
